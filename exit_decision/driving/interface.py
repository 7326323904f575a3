"""The one driver interface: ``decide(graph, snapshot, time) -> StepDecision``.

A driver is made for one environment's road and shield, with its mode bound when it is made or
when the mode changes (``set_mode``, a ``model.modes.Mode``); ``reset`` ends whatever it holds
from step to step (an episode's start, a mode switch). The decision node, replay, evaluation,
the sweeps and training all drive through it, and ``episode.play_episode`` is the one loop that
steps the environment with it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from exit_decision.agents.options import CavOption
from exit_decision.graph import TrafficGraph
from exit_decision.model.modes import Mode
from exit_decision.shield_overrides import ShieldOverride
from exit_decision.traffic import CavCommand, TrafficSnapshot


@dataclass(frozen=True)
class StepDecision:
    """What a driver decided at one decision step."""
    commands: dict[str, CavCommand]           # vehicle id -> its command until the next decision
    #: the grid's CAVs whose first choice the shield refused (over options the shield bounds the
    #: low level's command before it is made: no refused first choice)
    overrides: dict[str, ShieldOverride] = field(default_factory=dict)
    #: over options, the option each CAV holds (None on the grid and for SUMO's drivers)
    options: dict[str, CavOption] | None = None
    #: each CAV's action in the driver's action space (a grid action, or the option it holds);
    #: empty for drivers that act off both (SUMO's, the low level's direct commands)
    actions: dict[str, int] = field(default_factory=dict)
    #: on the grid, the shield's mask each CAV chose under (training's replay keeps it)
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    #: over options, the CAVs that began an option at this step (only their choice is learnt from)
    began: frozenset[str] = frozenset()


class Driver(Protocol):
    name: str

    def reset(self) -> None:
        """Ends whatever is held from step to step: an episode's start, a mode switch."""

    def set_mode(self, mode: Mode) -> None:
        """Drive for ``mode`` from the next decision on (a fixed driver ignores it; a policy
        refuses a mode it cannot drive, with PolicyError, and ends every held option)."""

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot, time: float) -> StepDecision:
        """The commands of the graph's CAVs at simulation ``time`` [s]; KeyError when a CAV of
        the graph is not in ``snapshot``."""
