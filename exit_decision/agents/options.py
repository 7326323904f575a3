"""Options, the second action space (issue 28): per CAV, a lane intent x a driving style.

An option is held until it ends: after ``hold_time``, when its lane change is done, when the
lane planner takes the CAV over (it leaves its route) or gives it back, or at a mode switch
(``OptionExecutor.reset``). At every decision step the project's rule-based driver, with the
style's parameters (config/env.yaml ``options.styles`` over ``options.low_level`` over
``rule_based``), turns each held
option into an acceleration and lane-change command under the shield (``RuleBasedDriver.command``);
SUMO's car following and lane changing are never used for these CAVs.

Masks depend on the road and the planner only, never on the traffic or the mode: a lane
intent is allowed where its lane exists and, with the planner on, keeps the CAV on its route;
a CAV the planner drives may only choose ``keep`` or ``route`` options (its lane is the
planner's, its style ``planner_style`` or its option's); near the first exit a CAV not yet in
the lane it needs may only choose ``route`` options (``route_only_before``). A constant option (one style, ``route``, for every CAV
and the whole episode) is a fixed driver of this low level. The shield keeps the last word on every command.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.rule_based import RuleBasedDriver, shielded_commands
from exit_decision.agents.shield import Shield
from exit_decision.config import ProjectConfig
from exit_decision.traffic import CavCommand, TrafficSnapshot, VehicleState

#: the lane change an intent makes once; ``route`` has none of its own: the CAV follows the
#: route's lane plan (the rule-based driver's: towards the route lane nearest the exit lane)
LANE_CHANGE_OF_INTENT = {'keep': 0, 'left': 1, 'right': -1, 'route': None}


@dataclass(frozen=True, slots=True)
class Option:
    lane_intent: str    # keep | left | right | route
    style: str          # a key of options.styles


@dataclass(frozen=True, slots=True)
class CavOption:
    """What a CAV holds, as published and recorded (/exit_decision/cav_options): the option,
    its index and when it began [s, simulation time]."""
    option: Option
    index: int
    started: float


@dataclass(frozen=True, slots=True)
class HeldOption:
    index: int
    start_lane: int
    target_lane: int | None   # None: the route's lane plan
    started: float      # [s] simulation time
    planned: bool       # the lane planner drove the CAV when the option began


class OptionSpace:
    """The options of a project config: their indices, masks and drivers."""

    def __init__(self, config: ProjectConfig, shield: Shield, planner: LanePlanner | None):
        options = config.env.options
        self.hold_time, self.route_only_before, self.planner_style = (options.hold_time, options.route_only_before,
                                                                      options.planner_style)
        self.options = tuple(Option(intent, style) for intent in options.lane_intents for style in options.styles)
        self.size = len(self.options)
        self.shield, self.geometry, self.planner = shield, shield.geometry, planner
        self.drivers = {style: RuleBasedDriver(shield.grid, shield, shield.geometry, config.scenario.road.ramp_speed_limit,
                                               options.style(config.env.rule_based, style))
                        for style in options.styles}

    def index(self, lane_intent: str, style: str) -> int:
        try:
            return self.options.index(Option(lane_intent, style))
        except ValueError:
            raise ValueError(f'no option ({lane_intent}, {style}); options: '
                             f'{", ".join(f"({o.lane_intent}, {o.style})" for o in self.options)}') from None

    def planned(self, vehicle: VehicleState) -> bool:
        """Does the lane planner drive this CAV's lane now (it is off its route)?"""
        return self.planner is not None and not self.planner.on_route(vehicle)

    def route_only(self, vehicle: VehicleState) -> bool:
        """Only ``route`` intents: from ``route_only_before`` metres before the first exit's
        junction ends, a CAV on the highway not in the route lane nearest the exit lane (lane 1
        there, lane 0 after it) follows the route's lane plan (measured: CAVs that kept lane 2,
        or lane 1 past the first exit, missed the target exit when the planner took them late)."""
        geometry = self.geometry
        start = geometry.first_exit.merge_done_at - self.route_only_before
        return (self.route_only_before > 0 and vehicle.on_highway and vehicle.position >= start
                and vehicle.position < geometry.target_exit.diverge_at
                and vehicle.lane_index != min(geometry.route_lanes(vehicle.position)))

    def mask(self, vehicle: VehicleState) -> np.ndarray:
        """(size,) bool: the options this CAV may begin now (road and planner only)."""
        allowed = np.zeros(self.size, dtype=bool)
        planned = self.planned(vehicle)
        route_only = self.route_only(vehicle)
        for index, option in enumerate(self.options):
            change = LANE_CHANGE_OF_INTENT[option.lane_intent]
            if route_only:
                allowed[index] = change is None
            elif not change:
                allowed[index] = True
            elif not planned and self.geometry.lane_change_exists(vehicle, change):
                allowed[index] = self.planner is None or self.planner.on_route(vehicle, vehicle.lane_index + change)
        return allowed


class OptionExecutor:
    """The options each CAV holds, when they end, and their commands at a decision step."""

    def __init__(self, space: OptionSpace):
        self.space = space
        self.held: dict[str, HeldOption] = {}

    def reset(self) -> None:
        """Every option ends: a new episode, or a mode switch."""
        self.held.clear()

    def ended(self, vehicle: VehicleState, time: float) -> bool:
        held = self.held.get(vehicle.vehicle_id)
        return (held is None or time - held.started >= self.space.hold_time - 1e-9
                or (held.target_lane not in (None, held.start_lane) and vehicle.lane_index == held.target_lane)
                or held.planned != self.space.planned(vehicle))

    def choose(self, snapshot: TrafficSnapshot, cav_ids: Sequence[str], time: float,
               chooser: Callable[[VehicleState, np.ndarray], int]) -> dict[str, int]:
        """Begins a new option for every CAV whose option ended, ``chooser(vehicle, mask)``
        picking it; returns CAV id -> the option it holds. Options of CAVs gone are dropped.
        KeyError, before any option changes, when a CAV is not in ``snapshot``."""
        vehicles = [snapshot.by_id[vehicle_id] for vehicle_id in cav_ids]
        present = set(cav_ids)
        self.held = {vid: held for vid, held in self.held.items() if vid in present}
        for vehicle in vehicles:
            vehicle_id = vehicle.vehicle_id
            if not self.ended(vehicle, time):
                continue
            mask = self.space.mask(vehicle)
            index = chooser(vehicle, mask)
            if not mask[index]:
                raise ValueError(f'{vehicle_id}: option {index} is masked')
            change = LANE_CHANGE_OF_INTENT[self.space.options[index].lane_intent]
            target = None if change is None else vehicle.lane_index + change
            self.held[vehicle_id] = HeldOption(index, vehicle.lane_index, target, time, self.space.planned(vehicle))
        return {vid: self.held[vid].index for vid in cav_ids}

    def held_options(self) -> dict[str, CavOption]:
        """The option each CAV holds now, as published."""
        return {vid: CavOption(self.space.options[held.index], held.index, held.started)
                for vid, held in self.held.items()}

    def commands(self, snapshot: TrafficSnapshot, cav_ids: Sequence[str]) -> dict[str, CavCommand]:
        """The held options' commands under the shield: the style's driver towards the option's
        lane (the route's lane plan for a ``route`` option and for a CAV the planner drives)."""
        space = self.space

        def command_of(vehicle: VehicleState, mask: np.ndarray) -> CavCommand:
            held = self.held[vehicle.vehicle_id]
            planned = space.planned(vehicle)
            style = space.planner_style if planned and space.planner_style else space.options[held.index].style
            return space.drivers[style].command(vehicle, mask, snapshot, None if planned else held.target_lane)

        return shielded_commands(space.shield, snapshot, cav_ids, command_of)
