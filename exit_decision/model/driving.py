"""A policy driving the CAVs decision step by decision step, on the grid or over options: the
one path of the decision node, replay and evaluation from a policy's choice to the commands.

On the grid each decision is the shield's greedy choice of the policy's Q values. Over options
the driver holds each CAV's option from step to step (``agents.options.OptionExecutor``): the
CAVs whose option ended begin the allowed option of highest Q value, and the rule-based low
level turns every held option into a command under the shield. ``reset`` ends every option:
at an episode's start and at a mode switch (issue 28).
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.options import CavOption, OptionExecutor, OptionSpace
from exit_decision.agents.shield import Shield
from exit_decision.config import ProjectConfig
from exit_decision.graph import FEATURE_SETS, TrafficGraph
from exit_decision.model.names import Planned
from exit_decision.model.policy import PolicyController, load_controllers
from exit_decision.shield_overrides import ShieldOverride, shield_overrides
from exit_decision.traffic import CavCommand, TrafficSnapshot


@dataclass(frozen=True)
class StepDecision:
    commands: dict[str, CavCommand]           # vehicle id -> its command until the next decision
    overrides: dict[str, ShieldOverride]      # the grid's CAVs whose first choice the shield refused
    #: over options, the option each CAV holds (None on the grid); the shield bounds the low
    #: level's command before it is made, so options have no refused first choice
    options: dict[str, CavOption] | None = None


class PolicyDriver:
    """``decide(graph, snapshot, weights, time)`` for one controller, across the steps of an episode."""

    def __init__(self, controller: PolicyController, config: ProjectConfig):
        self.controller = controller
        self.grid = controller.shield.grid
        self.executor = OptionExecutor(OptionSpace(config, controller.shield, controller.planner)) \
            if controller.policy.action_space == 'options' else None

    def reset(self) -> None:
        """Every held option ends (a new episode, or a mode switch); nothing on the grid."""
        if self.executor is not None:
            self.executor.reset()

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot, weights: np.ndarray | None,
               time: float) -> StepDecision:
        """The commands of the graph's CAVs at simulation ``time`` [s], for ``weights`` (None: the
        policy's own mode). KeyError when a CAV of the graph is not in ``snapshot``."""
        if self.executor is None:
            decision = self.controller.decide(graph, snapshot, weights)
            return StepDecision({vid: self.grid.command(index) for vid, index in decision.actions.items()},
                                shield_overrides(decision, self.grid))
        cav_ids = graph.cav_ids()
        self.executor.choose(snapshot, cav_ids, time, self.controller.option_chooser(graph, snapshot, weights))
        return StepDecision(self.executor.commands(snapshot, cav_ids), {}, self.executor.held_options())


def load_drivers(config: ProjectConfig, policy_dir: Path, planned_policies: Iterable[Planned], shield: Shield,
                 warm_weights: np.ndarray) -> dict[Planned, PolicyDriver]:
    """The drivers of the planned policies (``policy.load_controllers``, with the config's lane
    planner), each network run once on an empty graph: the first forward pass is slow, and
    should not be the first decision's. PolicyError, naming the file, as ``load_controllers``."""
    controllers = load_controllers(config, policy_dir, planned_policies, shield, LanePlanner.of(config, shield))
    n, f = config.graph.max_vehicles, len(FEATURE_SETS[config.graph.feature_set])
    idle = TrafficGraph(np.zeros((n, f), np.float32), np.zeros((n, n), np.uint8), np.zeros(n, bool), ('',) * n)
    for controller in controllers.values():
        controller.policy.q_values(idle, TrafficSnapshot([]), warm_weights if controller.policy.conditioned else None)
    return {key: PolicyDriver(controller, config) for key, controller in controllers.items()}
