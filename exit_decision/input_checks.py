"""Checks of input that comes from outside (ROS topics, bags) against the scenario.

ROS-free: the nodes convert a message to the core's types and ask these functions whether
it can be used. Three kinds of check, each all-or-nothing (a message with any bad field is
rejected whole and changes no state):

- ``StateLimits.check``: every field of the vehicle states of one step against the
  scenario: known (edge, lane) pairs (so ``lane_index`` 3, -1, 127 or -128 never reaches
  the graph's lane one-hot), ids named after their class and within its count, classes,
  finite values within what the road and the vehicle types allow, the step length.
- ``CommandLimits.sanitize``: CAV commands; a non-finite acceleration or a lane change
  outside the action grid rejects the message, a finite acceleration outside the grid is
  clamped to it (and counted by the caller).
- ``StepGate``: which (episode, step) a stream may carry next. The episode changes only
  after ``announce`` (the bridge's or the player's EVENT_STARTED), at the first message of
  the announced episode (``begins``), so an EVENT_STARTED that no message of its episode
  follows (stray, forged) changes nothing; within an episode steps go up, by at most
  ``max_gap`` at a time, never past the scenario's step cap. A message that cannot follow is
  rejected without moving the gate, so one bad sequence number never changes what the later
  good messages get. A node that really missed more than ``max_gap`` steps (stalled, lost
  messages) follows again after ``resync`` consecutive messages that follow each other.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property

from exit_decision.traffic import (CAV, INTENTION_KEEP, INTENTION_LEFT, INTENTION_RIGHT, CavCommand, VehicleState,
                                   vehicle_id_of)

#: [m] SUMO's default lane width (the generated network sets none): the largest lateral offset
LANE_WIDTH = 3.2
#: accelerations up to this factor times the largest the vehicle types and the action grid
#: allow are physically plausible readings; beyond, the value is garbage
ACCELERATION_MARGIN = 2.0
#: [m/s] speeds up to the class's max_speed plus this are accepted (SUMO never exceeds it)
SPEED_TOLERANCE = 1.0
INTENTIONS = (INTENTION_RIGHT, INTENTION_KEEP, INTENTION_LEFT)
#: episode starts a gate keeps announced at once, the oldest dropped first: forged starts sent
#: during an episode cannot push out the bridge's next start, which comes after them (more than
#: this many sent between the bridge's start and its episode's first message could)
MAX_ANNOUNCED = 1000


class InputError(ValueError):
    """Input that cannot be used; the text names the field and what is wrong with it."""


@dataclass(frozen=True)
class StateLimits:
    """What the vehicle states of one step may contain in this scenario."""
    lanes: frozenset[tuple[str, int]]           # (edge_id, lane_index) pairs of the road
    class_counts: Mapping[str, int]             # vehicle class -> vehicles of it per episode
    lengths: Mapping[str, float]                # vehicle class -> length [m]
    max_speeds: Mapping[str, float]             # vehicle class -> max speed [m/s]
    position_max: float                         # [m] farthest front-bumper position
    speed_limit_max: float                      # [m/s] highest lane speed limit
    acceleration_range: tuple[float, float]     # [m/s^2]
    step_length: float                          # [s]
    max_steps: int
    max_vehicles: int                           # vehicles one message may carry
    highway_edges: frozenset[str]               # the highway sections' edge ids (any other edge: a ramp)

    @classmethod
    def of(cls, config, geometry) -> StateLimits:
        """From the project config and its ``RoadGeometry`` (every lane's edge, index and
        offset along the road; the road's length)."""
        scenario, road = config.scenario, config.scenario.road
        road_length = geometry.road_length
        ramps = [lane.offset for lane in geometry.lanes.values() if not lane.on_highway]
        types = scenario.vehicle_types
        braking = max([t.emergency_decel for t in types.values()] + [-config.env.actions.acceleration_min])
        speeding_up = max([t.accel for t in types.values()] + [config.env.actions.acceleration_max])
        return cls(
            lanes=frozenset((lane.edge_id, lane.lane_index) for lane in geometry.lanes.values()),
            class_counts={name: c.count for name, c in scenario.vehicle_classes.items()},
            lengths={name: t.length for name, t in types.items()},
            max_speeds={name: t.max_speed for name, t in types.items()},
            position_max=max([road_length] + [offset + road.ramp_length for offset in ramps]),
            speed_limit_max=max(road.highway_speed_limit, road.ramp_speed_limit),
            acceleration_range=(-ACCELERATION_MARGIN * braking, ACCELERATION_MARGIN * speeding_up),
            step_length=scenario.step_length, max_steps=scenario.max_steps,
            max_vehicles=min(scenario.total_vehicles, config.graph.max_vehicles),
            highway_edges=frozenset(geometry.sections))

    def check(self, vehicles: Sequence[VehicleState], step: int | None = None,
              step_length: float | None = None) -> None:
        """Raise InputError naming the first field that does not fit the scenario."""
        if step is not None and not 0 <= step <= self.max_steps:
            raise InputError(f'step {step} is outside 0..{self.max_steps} (the scenario\'s step cap)')
        if step_length is not None and not math.isclose(step_length, self.step_length, rel_tol=1e-9):
            raise InputError(f'step_length {step_length!r} is not the scenario\'s {self.step_length}')
        if len(vehicles) > self.max_vehicles:
            raise InputError(f'{len(vehicles)} vehicles, more than the {self.max_vehicles} the scenario and '
                             f'the graph allow')
        seen = set()
        for vehicle in vehicles:
            self.check_vehicle(vehicle)
            if vehicle.vehicle_id in seen:
                raise InputError(f'vehicle {vehicle.vehicle_id!r} appears twice')
            seen.add(vehicle.vehicle_id)

    @cached_property
    def _ranges(self) -> dict[str, tuple[tuple[str, float, float], ...]]:
        """Per class, (field, low, high) of the numeric fields: made once, used for every vehicle
        of every step. The bounds are finite, so NaN and infinities fall outside them."""
        return {name: (('position', 0.0, self.position_max), ('lateral_offset', -LANE_WIDTH, LANE_WIDTH),
                       ('speed', 0.0, max_speed + SPEED_TOLERANCE), ('acceleration', *self.acceleration_range),
                       ('lane_speed_limit', 0.0, self.speed_limit_max + 1e-6))
                for name, max_speed in self.max_speeds.items()}

    @cached_property
    def _edges(self) -> frozenset[str]:
        return frozenset(edge for edge, _ in self.lanes)

    @cached_property
    def _ids(self) -> frozenset[tuple[str, str]]:
        """Every (vehicle_id, vehicle_class) an episode may have (``vehicle_id_of``): one look-up
        instead of parsing each id of each step."""
        return frozenset((vehicle_id_of(name, serial), name)
                         for name, count in self.class_counts.items() for serial in range(count))

    def check_vehicle(self, v: VehicleState) -> None:
        if v.vehicle_class not in self.class_counts:
            raise _bad_field(v, 'vehicle_class', f'a class of the scenario ({", ".join(self.class_counts)})')
        if (v.vehicle_id, v.vehicle_class) not in self._ids:
            raise _bad_field(v, 'vehicle_id', f'<class>_<n> with its class {v.vehicle_class} and n below '
                                              f'{self.class_counts[v.vehicle_class]}')
        if (v.edge_id, v.lane_index) not in self.lanes:
            raise InputError(f'vehicle {v.vehicle_id!r}: lane_index {v.lane_index} on edge_id {v.edge_id!r} '
                             f'is no lane of the road')
        if v.route_target not in self._edges:
            raise _bad_field(v, 'route_target', 'an edge of the road')
        for field, low, high in self._ranges[v.vehicle_class]:
            if not low <= getattr(v, field) <= high:
                raise _bad_field(v, field, f'finite within [{low:g}, {high:g}]')
        if not math.isclose(v.length, self.lengths[v.vehicle_class], rel_tol=1e-6):
            raise _bad_field(v, 'length', f'the {v.vehicle_class} length {self.lengths[v.vehicle_class]:g}')
        if v.intention not in INTENTIONS:
            raise _bad_field(v, 'intention', 'one of -1, 0, 1')
        if v.controlled and v.vehicle_class != CAV:
            raise _bad_field(v, 'controlled', 'false for a human-driven class')


def _bad_field(v: VehicleState, field: str, allowed: str) -> InputError:
    return InputError(f'vehicle {v.vehicle_id!r}: {field} {getattr(v, field)!r} is not {allowed}')


@dataclass(frozen=True)
class CommandLimits:
    """What a CAV command may ask for: the action grid's lane changes and acceleration range."""
    lane_changes: tuple[int, ...]
    acceleration_min: float
    acceleration_max: float

    @classmethod
    def of(cls, actions) -> CommandLimits:
        """From the action grid config (``config.env.actions``)."""
        return cls(tuple(actions.lane_changes), actions.acceleration_min, actions.acceleration_max)

    def sanitize(self, commands: Mapping[str, CavCommand]) -> tuple[dict[str, CavCommand], int]:
        """The commands with accelerations clamped to the grid, and how many were clamped.
        Raise InputError (nothing clamped, nothing kept) on a non-finite acceleration or a
        lane change the grid does not have."""
        result, clamped = {}, 0
        for vehicle_id, command in commands.items():
            if not vehicle_id:
                raise InputError('a command has an empty vehicle_id')
            if command.lane_change not in self.lane_changes:
                raise InputError(f'{vehicle_id!r}: lane_change {command.lane_change} is not one of {self.lane_changes}')
            if not math.isfinite(command.acceleration):
                raise InputError(f'{vehicle_id!r}: acceleration {command.acceleration!r} is not finite')
            acceleration = min(max(command.acceleration, self.acceleration_min), self.acceleration_max)
            clamped += acceleration != command.acceleration
            result[vehicle_id] = command if acceleration == command.acceleration else \
                CavCommand(command.lane_change, acceleration)
        return result, clamped


class StepGate:
    """The (episode, step) sequence of one stream (see the module docstring)."""

    def __init__(self, max_step: int, max_gap: int = 10, resync: int = 3):
        self.max_step, self.max_gap, self.resync = max_step, max_gap, resync
        self.episode: int | None = None      # None until the first start
        self.last = -1                       # last accepted step of the episode (-1: none yet)
        self.announced: dict[int, int] = {}  # episodes whose EVENT_STARTED came -> self.last then; none begun yet
        self._chain: list[tuple[int, int]] = []   # consecutive messages too far ahead, each following the one before

    def announce(self, episode: int) -> None:
        """An EVENT_STARTED of ``episode`` (the bridge's or the player's). With no episode yet the
        gate follows it at once. Otherwise the current episode's messages still follow, and
        ``episode`` (or another announced since) begins with its first message that can start
        it (``begins``): a stray or forged EVENT_STARTED, before or after the bridge's, changes
        nothing while no message of its episode follows it."""
        if self.episode is None:
            self.start(episode)
            return
        self.announced.pop(episode, None)
        self.announced[episode] = self.last
        if len(self.announced) > MAX_ANNOUNCED:
            del self.announced[next(iter(self.announced))]

    def start(self, episode: int) -> None:
        """Follow ``episode`` from its step 0 now, so a late message of the pass before (a looped
        bag's last steps arriving after the next pass began) is refused, not taken as the new
        pass's first. A resync under way into ``episode`` goes on."""
        self.episode, self.last = episode, -1
        self.announced.clear()
        self._chain = [entry for entry in self._chain if entry[0] == episode]

    def begins(self, episode: int, step: int) -> bool:
        """Whether a message of (episode, step), if taken, begins the announced episode (its
        caller then starts its per-episode state afresh): one of the episode's first ``max_gap``
        steps, a step back when the same episode starts again (a looped bag's next pass, while
        the pass before has not gone on for more than ``max_gap`` steps since its start came), or
        one that ends a resync (a node that joins late)."""
        announced_at = self.announced.get(episode)
        if announced_at is None or not 0 <= step <= self.max_step:
            return False
        if episode == self.episode and (step > self.last or self.last > announced_at + self.max_gap):
            return False                     # it follows the pass that is running, which went on after that start
        return step < self.max_gap or self._resyncs(episode, step)

    def check(self, episode: int, step: int) -> str | None:
        """Why a message of (episode, step) cannot come next, or None if it can. Changes no
        state: call ``accept`` once the whole message is found valid."""
        if self.episode is None:
            return f'episode {episode}: no episode has started'
        if self.begins(episode, step):
            return None
        if episode != self.episode:
            return f'episode {episode} is not the current episode {self.episode}'
        if not 0 <= step <= self.max_step:
            return f'step {step} is outside 0..{self.max_step}'
        if self.last < step <= self.last + self.max_gap:
            return None
        if step <= self.last:
            return f'step {step} does not follow step {self.last}'
        if self._resyncs(episode, step):
            return None     # the stream really moved on: follow it
        return f'step {step} jumps more than {self.max_gap} steps past step {self.last}'

    def _resyncs(self, episode: int, step: int) -> bool:
        """(episode, step) would be the ``resync``-th of consecutive refused messages that follow each other."""
        chain = self._chain if self._chain and self._follows(self._chain[-1], episode, step) else []
        return len(chain) + 1 >= self.resync

    def _follows(self, previous: tuple[int, int], episode: int, step: int) -> bool:
        return previous[0] == episode and previous[1] < step <= previous[1] + self.max_gap

    def refuse(self, episode: int, step: int) -> str | None:
        """``check``, and a refused message remembered for a resync (``note_rejected``)."""
        reason = self.check(episode, step)
        if reason:
            self.note_rejected(episode, step)
        return reason

    def note_rejected(self, episode: int, step: int) -> None:
        """Remember a message rejected only for jumping too far ahead (it may start a resync):
        past the running pass's last step plus ``max_gap``, or past the announced episode's first
        ``max_gap`` steps. What later messages are accepted by ``check`` does not depend on it
        unless ``resync`` such messages in a row follow each other."""
        if not 0 <= step <= self.max_step:
            return
        ahead = (episode == self.episode and step > self.last + self.max_gap) or (
            episode in self.announced and step >= self.max_gap and (episode != self.episode or step <= self.last))
        if not ahead:
            return
        if self._chain and self._follows(self._chain[-1], episode, step):
            self._chain.append((episode, step))
        else:
            self._chain = [(episode, step)]

    def accept(self, episode: int, step: int) -> int:
        """Take a message of (episode, step) (``check`` said it can come next); the number of
        steps skipped since the last one taken (or since the episode's start)."""
        if self.begins(episode, step):
            self.start(episode)
        skipped = step - self.last - 1
        self.last, self._chain = step, []
        return skipped
