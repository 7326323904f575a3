"""The road in the plane (frame ``map``, metres) and where each vehicle is on it.

x runs along the highway and equals the position along the road (front bumper, from the
start of the first highway edge, junction lanes included, as ``VehicleState.position``); y points left,
lane 0 (rightmost) at y = 0. Lanes are ``LANE_WIDTH`` apart (the width the network is built
with); each exit ramp's start, end and direction come from the road geometry (read from the
generated SUMO network), so the drawing follows the simulated road.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from exit_decision.config import RoadConfig
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.scenario.sumo_inputs import LANE_WIDTH
from exit_decision.traffic import CAV, HV1, HV2, HV3, VEHICLE_CLASSES, VehicleState

#: one colour per vehicle class (RGB in [0, 1]), the same in markers, diagrams and clips
CLASS_COLOURS = {CAV: (0.12, 0.47, 0.71), HV1: (0.17, 0.63, 0.17), HV2: (1.0, 0.5, 0.05),
                 HV3: (0.58, 0.40, 0.74)}
COLLISION_COLOUR = (0.84, 0.15, 0.16)
ROAD_COLOUR = (0.35, 0.35, 0.35)
VEHICLE_WIDTH = 1.8   # [m] drawn width of every vehicle (the states carry lengths only)
assert set(CLASS_COLOURS) == set(VEHICLE_CLASSES)


@dataclass(frozen=True, slots=True)
class Ramp:
    edge_id: str                  # the ramp's edge
    start: float                  # [m] position where its junction lane leaves lane 0
    end: float                    # [m] position of its end (vehicles arrive there)
    direction: tuple[float, float]  # unit vector in the plane


@dataclass(frozen=True, slots=True)
class Pose:
    x: float
    y: float
    yaw: float                    # [rad], 0 = along the highway


@dataclass(frozen=True)
class RoadLayout:
    lane_count: int
    lane_spacing: float           # [m] between lane centres
    road_length: float            # [m] position of the end of the last highway edge
    ramps: dict[str, Ramp]
    last_section: str             # the last highway edge's name (labelled at its end)

    @classmethod
    def of(cls, geometry: RoadGeometry, road: RoadConfig) -> RoadLayout:
        ramps = {e.ramp: Ramp(e.ramp, e.diverge_at, geometry.lanes[f'{e.ramp}_0'].offset + road.ramp_length,
                              e.direction) for e in geometry.exits.values()}
        return cls(geometry.lane_count, LANE_WIDTH, geometry.road_length, ramps, geometry.sections[-1])

    def lane_y(self, lane_index: int) -> float:
        return lane_index * self.lane_spacing

    def along(self, edge_id: str, position: float) -> Pose:
        """The point of the road at ``position`` on ``edge_id``'s corridor (lane 0 for a ramp)."""
        ramp = self.ramps.get(edge_id)
        if ramp is None or position <= ramp.start:
            return Pose(position, 0.0, 0.0)
        s = position - ramp.start
        dx, dy = ramp.direction
        return Pose(ramp.start + s * dx, s * dy, math.atan2(dy, dx))

    def place(self, vehicle: VehicleState) -> Pose:
        """Centre and heading of a vehicle's box (the state gives its front bumper)."""
        centre = vehicle.position - vehicle.length / 2
        if vehicle.on_highway or vehicle.edge_id not in self.ramps:
            return Pose(centre, self.lane_y(vehicle.lane_index) + vehicle.lateral_offset, 0.0)
        pose = self.along(vehicle.edge_id, centre)
        return Pose(pose.x, pose.y, pose.yaw)

    def route_end(self, vehicle: VehicleState) -> float:
        """Position where the vehicle's route ends (where SUMO lets it arrive)."""
        ramp = self.ramps.get(vehicle.route_target)
        return ramp.end if ramp else self.road_length

    def lines(self) -> list[tuple[str, list[tuple[float, float]]]]:
        """Lane boundaries and ramp edges as named polylines."""
        half = self.lane_spacing / 2
        lines = [(f'lane boundary {i}', [(0.0, self.lane_y(i) - half), (self.road_length, self.lane_y(i) - half)])
                 for i in range(self.lane_count + 1)]
        for ramp in self.ramps.values():
            dx, dy = ramp.direction
            length = ramp.end - ramp.start
            for side in (-half, half):   # offset perpendicular to the ramp's direction
                ox, oy = -dy * side, dx * side
                lines.append((f'{ramp.edge_id} edge', [(ramp.start + ox, oy), (ramp.start + dx * length + ox,
                                                                                 dy * length + oy)]))
        return lines

    def labels(self) -> list[tuple[str, float, float]]:
        """Edge names where they end: each exit and the highway's end."""
        labels = [(ramp.edge_id, *self._end_point(ramp)) for ramp in self.ramps.values()]
        return labels + [(self.last_section, self.road_length, self.lane_y(self.lane_count - 1) + 2 * self.lane_spacing)]

    def _end_point(self, ramp: Ramp) -> tuple[float, float]:
        pose = self.along(ramp.edge_id, ramp.end)
        return pose.x, pose.y - 2 * self.lane_spacing

    def bounds(self, margin: float = 8.0) -> tuple[float, float, float, float]:
        """x0, x1, y0, y1 around the whole road."""
        ends = [self._end_point(r) for r in self.ramps.values()]
        y_low = min([0.0, *(y for _, y in ends)]) - margin
        y_high = self.lane_y(self.lane_count - 1) + 3 * self.lane_spacing + margin
        return -margin, self.road_length + margin, y_low, y_high
