"""Vehicle states and the neighbour search shared by the simulation, graph, reward and masks.

A vehicle's *corridor* is what it can have a leader or follower in: a highway lane (the
same lane index across the highway sections) or a ramp. Positions are front-bumper distances
along the road from the start of the first section. Edge names are the scenario config's
(``RoadConfig.names``); nothing here knows them.
"""
from __future__ import annotations

import bisect
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

from exit_decision.config.schemas import CAV, HV1, HV2, HV3, VEHICLE_CLASSES  # noqa: F401 (the core's names)

INTENTION_RIGHT, INTENTION_KEEP, INTENTION_LEFT = -1, 0, 1
#: The corridor name of the highway's lanes: ``(HIGHWAY, lane_index)``. Empty, so no edge (a
#: ramp's corridor is ``(edge_id, 0)``) can be called the same.
HIGHWAY = ''


def vehicle_id_of(vehicle_class: str, serial: int) -> str:
    """The id of the ``serial``-th vehicle (from 0) of a class in an episode: ``CAV_3``."""
    return f'{vehicle_class}_{serial}'


@dataclass(frozen=True, slots=True)
class VehicleState:
    """One vehicle at one step; mirrors exit_decision_msgs/VehicleState, plus ``on_highway``,
    which the road gives (the message carries only the edge id)."""
    vehicle_id: str
    vehicle_class: str          # HV1 | HV2 | HV3 | CAV
    lane_index: int             # 0 = rightmost; 0 on a ramp
    edge_id: str                # a highway section or a ramp (the edge ahead while on a junction)
    position: float             # [m] front bumper, from the start of the first section
    lateral_offset: float       # [m]
    speed: float                # [m/s]
    acceleration: float         # [m/s^2]
    length: float               # [m]
    lane_speed_limit: float     # [m/s]
    intention: int              # INTENTION_* (last commanded lane change for a CAV)
    route_target: str           # last edge of the current route
    controlled: bool            # commanded by the decision policy
    on_highway: bool            # on a highway section, not on a ramp (from the road's names)

    @property
    def is_cav(self) -> bool:
        return self.vehicle_class == CAV

    @property
    def corridor(self) -> tuple[str, int]:
        return (HIGHWAY, self.lane_index) if self.on_highway else (self.edge_id, 0)


class Neighbours(NamedTuple):
    """Closest vehicles ahead and behind in one corridor, with bumper-to-bumper gaps [m]. (A
    tuple: the shield and the graph make thousands a second, a frozen dataclass cost 3x.)"""
    leader: VehicleState | None
    leader_gap: float
    follower: VehicleState | None
    follower_gap: float


class TrafficSnapshot:
    """All vehicles of one step, indexed by corridor for leader/follower look-ups."""

    def __init__(self, vehicles: Iterable[VehicleState]):
        self.vehicles = list(vehicles)
        self.by_id = {v.vehicle_id: v for v in self.vehicles}
        lanes: dict[tuple[str, int], list[VehicleState]] = {}
        for vehicle in self.vehicles:
            lanes.setdefault(vehicle.corridor, []).append(vehicle)
        self._lanes = {key: sorted(group, key=lambda v: v.position) for key, group in lanes.items()}
        self._positions = {key: [v.position for v in group] for key, group in self._lanes.items()}

    def with_vehicle(self, vehicle: VehicleState) -> TrafficSnapshot:
        """A copy with one more vehicle; only its corridor is re-sorted (the shield adds a
        virtual vehicle per reserved gap, several times per decision)."""
        copy = TrafficSnapshot.__new__(TrafficSnapshot)
        copy.vehicles = [*self.vehicles, vehicle]
        copy.by_id = {**self.by_id, vehicle.vehicle_id: vehicle}
        copy._lanes, copy._positions = dict(self._lanes), dict(self._positions)
        key = vehicle.corridor
        index = bisect.bisect_right(self._positions.get(key, []), vehicle.position)
        copy._lanes[key] = [*self._lanes.get(key, [])[:index], vehicle, *self._lanes.get(key, [])[index:]]
        copy._positions[key] = [v.position for v in copy._lanes[key]]
        return copy

    def neighbours(self, corridor: tuple[str, int], position: float, length: float,
                   exclude: str | None = None) -> Neighbours:
        """Leader and follower of a vehicle (real or hypothetical) at ``position`` in ``corridor``."""
        group = self._lanes.get(corridor, ())
        ahead = bisect.bisect_left(self._positions.get(corridor, ()), position)
        behind = ahead - 1
        while ahead < len(group) and group[ahead].vehicle_id == exclude:
            ahead += 1
        while behind >= 0 and group[behind].vehicle_id == exclude:
            behind -= 1
        leader = group[ahead] if ahead < len(group) else None
        follower = group[behind] if behind >= 0 else None
        return Neighbours(leader, leader.position - leader.length - position if leader else float('inf'),
                          follower, position - length - follower.position if follower else float('inf'))

    def leader_pairs(self) -> Iterator[tuple[VehicleState, VehicleState, float]]:
        """(follower, leader, bumper gap [m]) of every vehicle that has a leader in its corridor:
        one pass over the sorted corridors, for metrics that look at every vehicle."""
        for group in self._lanes.values():
            for follower, leader in zip(group, group[1:]):
                yield follower, leader, leader.position - leader.length - follower.position

    def neighbours_of(self, vehicle: VehicleState, lane_offset: int = 0) -> Neighbours:
        """Neighbours of a vehicle in its own corridor, or in the highway lane ``lane_offset`` away."""
        if lane_offset == 0:
            corridor = vehicle.corridor
        else:
            corridor = (HIGHWAY, vehicle.lane_index + lane_offset)
        return self.neighbours(corridor, vehicle.position, vehicle.length, exclude=vehicle.vehicle_id)


@dataclass(frozen=True, slots=True)
class Arrival:
    vehicle_id: str
    vehicle_class: str
    exit_edge: str          # the last highway section or a ramp
    reached_target: bool    # left by the target exit (the CAVs' task)


@dataclass(frozen=True, slots=True)
class Collision:
    collider: str
    victim: str
    collider_class: str
    victim_class: str

    @property
    def involves_cav(self) -> bool:
        return CAV in (self.collider_class, self.victim_class)


@dataclass(slots=True)
class StepResult:
    """The state after a step, and the events of that step."""
    step: int
    time: float
    vehicles: list[VehicleState]
    arrivals: list[Arrival] = field(default_factory=list)
    collisions: list[Collision] = field(default_factory=list)
    braking_starts: list[str] = field(default_factory=list)   # emergency braking began this step
    lane_changers: list[str] = field(default_factory=list)    # vehicles that changed lane this step
    inserted: int = 0                                         # vehicles that entered so far
    waiting: int = 0                                          # drawn but not yet able to enter
    released: frozenset[str] = frozenset()                    # CAVs handed to SUMO after a missed exit
    terminated: bool = False                                  # every vehicle entered and left
    truncated: bool = False                                   # step cap reached


@dataclass(frozen=True, slots=True)
class CavCommand:
    lane_change: int        # -1 right, 0 keep, +1 left
    acceleration: float     # [m/s^2]
