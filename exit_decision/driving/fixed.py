"""The drivers that do not learn, and the two shapes every driver takes: a choice on the action
grid under the shield (``GridDriver``) and options held from step to step (``OptionDriver``).

The fixed drivers: the rule-based driver on the grid (the neutral driver of config/env.yaml's
``rule_based``, or a sanity sweep's), its low level's direct commands, a constant option (one
style on the route's lane plan for every CAV: a fixed driver of the options), held lanes, and
SUMO's own drivers (no commands: the environment's CAVs are SUMO's). ``by_name`` makes any of them
for an environment, by the names the tables use.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from exit_decision.actions import ActionGrid
from exit_decision.agents.options import OptionExecutor, OptionSpace
from exit_decision.agents.shield import Decision
from exit_decision.driving.interface import StepDecision
from exit_decision.env import ExitDecisionEnv
from exit_decision.graph import TrafficGraph
from exit_decision.model.modes import Mode
from exit_decision.shield_overrides import shield_overrides
from exit_decision.traffic import CavCommand, TrafficSnapshot, VehicleState

#: picks an option for a CAV whose option ended: (vehicle, its option mask) -> option index
OptionChooser = Callable[[VehicleState, np.ndarray], int]
#: the names of the fixed drivers (``by_name``) besides ``option_<style>``
SUMO, GRID_RULE_BASED, HELD_LANES = 'sumo', 'grid_rule_based', 'held_lanes'
OPTION_PREFIX = 'option_'


class FixedMode:
    """A driver whose driving is the same in every mode: ``set_mode`` changes nothing."""

    def set_mode(self, mode: Mode) -> None:
        pass


class GridDriver(FixedMode):
    """Chooses on the action grid: ``choose(graph, snapshot)`` is the shield's ``Decision``."""

    def __init__(self, name: str, grid: ActionGrid, choose: Callable[[TrafficGraph, TrafficSnapshot], Decision]):
        self.name, self.grid, self.choose = name, grid, choose

    def reset(self) -> None:
        pass

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot, time: float) -> StepDecision:
        decision = self.choose(graph, snapshot)
        return StepDecision({vid: self.grid.command(index) for vid, index in decision.actions.items()},
                            shield_overrides(decision, self.grid), actions=decision.actions, masks=decision.masks)


class OptionDriver(FixedMode):
    """Holds each CAV's option from step to step (``agents.options.OptionExecutor``): the CAVs
    whose option ended begin the one ``chooser_at(graph, snapshot)`` picks (made once per
    decision step), and the low level turns every held option into a command under the shield."""

    def __init__(self, name: str, space: OptionSpace, chooser_at: Callable[[TrafficGraph, TrafficSnapshot], OptionChooser]):
        self.name, self.space, self.chooser_at = name, space, chooser_at
        self.executor = OptionExecutor(space)

    def reset(self) -> None:
        """Every held option ends."""
        self.executor.reset()

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot, time: float) -> StepDecision:
        cav_ids, chooser, began = graph.cav_ids(), self.chooser_at(graph, snapshot), set()

        def choose(vehicle: VehicleState, mask: np.ndarray) -> int:
            began.add(vehicle.vehicle_id)
            return chooser(vehicle, mask)

        held = self.executor.choose(snapshot, cav_ids, time, choose)
        return StepDecision(self.executor.commands(snapshot, cav_ids), options=self.executor.held_options(),
                            actions=held, began=frozenset(began))


class CommandDriver(FixedMode):
    """Gives commands off the grid directly: ``commands_of(graph, snapshot)``."""

    def __init__(self, name: str, commands_of: Callable[[TrafficGraph, TrafficSnapshot], dict[str, CavCommand]]):
        self.name, self.commands_of = name, commands_of

    def reset(self) -> None:
        pass

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot, time: float) -> StepDecision:
        return StepDecision(self.commands_of(graph, snapshot))


def rule_based(env: ExitDecisionEnv, parameters=None, name: str = 'rule_based') -> GridDriver:
    """The rule-based driver on the grid: the neutral driver (``env.rule_based_driver``), or
    other ``parameters`` (the reward sanity sweep)."""
    return GridDriver(name, env.actions, env.rule_based_driver(parameters).decide)


def rule_based_low_level(env: ExitDecisionEnv, parameters=None, name: str = 'rule_based') -> CommandDriver:
    """The rule-based driver's own commands, off the grid (the options' low level)."""
    return CommandDriver(name, env.rule_based_driver(parameters).commands)


def constant_option(space: OptionSpace, style: str) -> OptionDriver:
    """One style on the route's lane plan for every CAV, the whole episode."""
    index = space.index('route', style)
    return OptionDriver(OPTION_PREFIX + style, space, lambda graph, snapshot: lambda vehicle, mask: index)


def held_lanes(env: ExitDecisionEnv) -> CommandDriver:
    """Every CAV keeps its lane and speed (``exit-decision run``'s policy CAVs)."""
    keep = env.actions.command(env.actions.index(0, 0.0))
    return CommandDriver(HELD_LANES, lambda graph, snapshot: dict.fromkeys(graph.cav_ids(), keep))


def sumo() -> CommandDriver:
    """SUMO's own drivers: no commands (the environment must be made with ``cav_driver='sumo'``)."""
    return CommandDriver(SUMO, lambda graph, snapshot: {})


def by_name(env: ExitDecisionEnv, name: str):
    """A fixed driver by its table name: ``sumo``, ``grid_rule_based``, ``held_lanes`` or
    ``option_<style>``; ValueError for another."""
    if name == SUMO:
        return sumo()
    if name == GRID_RULE_BASED:
        return rule_based(env, name=GRID_RULE_BASED)
    if name == HELD_LANES:
        return held_lanes(env)
    if name.startswith(OPTION_PREFIX):
        return constant_option(OptionSpace(env.config, env.shield, env.planner), name.removeprefix(OPTION_PREFIX))
    raise ValueError(f'no fixed driver {name!r}; allowed: {SUMO}, {GRID_RULE_BASED}, {HELD_LANES}, '
                     f'{OPTION_PREFIX}<style>')
