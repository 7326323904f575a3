"""Vehicle states -> the graph the policy sees (paper 000, Section 2.2). The only graph builder.

Training, evaluation and the ROS graph-builder node all call ``GraphBuilder.build`` so a
policy sees in ROS exactly what it saw in training.

- Rows are slots: a vehicle takes the lowest free slot when it first appears and keeps it
  for its whole life (so row i at t and t+m is the same vehicle); absent rows are zero.
- Features (``paper`` set, F = 8): speed / v_max, position / road length, lane one-hot (3),
  intention one-hot (change left, change right, keep).
- Adjacency (0/1, symmetric): each vehicle with itself; every CAV with every CAV; a CAV
  with an HV within the sensing range (longitudinal, any lane); never HV with HV.
- CAV mask: 1 on CAV rows. "CAV" here means a vehicle the policy controls
  (``VehicleState.controlled``): a CAV released to SUMO's driver after a missed exit is a
  human-driven vehicle from then on.

The ``relative`` feature set (ours; docs/design.md, "Graph") adds, for the lane to the right,
the own lane and the lane to the left: the bumper gap to the leader and to the follower
(/ 50 m, capped at 1; a lane that does not exist has gap 0) and their speed relative to the vehicle
(/ 10 m/s, clipped to [-1, 1]). The paper's absolute positions cannot resolve gaps.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from exit_decision.config import GraphConfig
from exit_decision.traffic import HIGHWAY, INTENTION_LEFT, INTENTION_RIGHT, TrafficSnapshot, VehicleState

PAPER_FEATURES = ('speed', 'position', 'lane_0', 'lane_1', 'lane_2',
                  'intention_left', 'intention_right', 'intention_keep')
#: lanes relative to the vehicle's own, for the relative features
LANE_OFFSETS = {'right': -1, 'own': 0, 'left': 1}
RELATIVE_FEATURES = PAPER_FEATURES + tuple(
    f'{side}_{what}' for side in LANE_OFFSETS
    for what in ('leader_gap', 'leader_speed', 'follower_gap', 'follower_speed'))
FEATURE_SETS = {'paper': PAPER_FEATURES, 'relative': RELATIVE_FEATURES}
GAP_SCALE = 50.0     # [m] gaps are divided by this and capped at 1 (no vehicle = 1)
SPEED_SCALE = 10.0   # [m/s] relative speeds are divided by this and clipped to [-1, 1]


class GraphCapacityError(RuntimeError):
    """More vehicles on the road than the graph has rows (raise graph.max_vehicles)."""


class GraphInputError(ValueError):
    """Vehicle states the graph cannot encode (a lane index outside the lane one-hot)."""


@dataclass(frozen=True, slots=True, eq=False)   # arrays: compare fields explicitly
class TrafficGraph:
    features: np.ndarray        # (N, F) float32
    adjacency: np.ndarray       # (N, N) uint8
    cav_mask: np.ndarray        # (N,) bool
    vehicle_ids: tuple[str, ...]  # N entries, '' for empty rows

    @property
    def num_nodes(self) -> int:
        return self.features.shape[0]

    def cav_rows(self) -> np.ndarray:
        return np.flatnonzero(self.cav_mask)

    def row_of(self) -> dict[str, int]:
        """Vehicle id -> its row (the slot it holds)."""
        return {vehicle_id: row for row, vehicle_id in enumerate(self.vehicle_ids) if vehicle_id}

    def cav_ids(self) -> list[str]:
        """Vehicle ids of the CAV rows, in row order."""
        return [self.vehicle_ids[row] for row in self.cav_rows()]


class GraphBuilder:
    """Stateful (slot assignment) builder of ``TrafficGraph`` from vehicle states."""

    def __init__(self, config: GraphConfig, road_length: float, speed_scale: float,
                 lane_count: int = 3):
        if lane_count != 3:
            raise ValueError(f'the paper feature set has a 3-lane one-hot; got lane_count={lane_count}')
        self.lane_count = lane_count
        self.config = config
        self.road_length = road_length
        self.speed_scale = speed_scale
        self.feature_names = FEATURE_SETS[config.feature_set]
        self.reset()

    @property
    def num_features(self) -> int:
        return len(self.feature_names)

    def reset(self) -> None:
        """Forget all slots (new episode)."""
        self._slot_of: dict[str, int] = {}
        self._free = list(range(self.config.max_vehicles))

    def slots(self, vehicles: Sequence[VehicleState]) -> list[int]:
        """Slots of the given vehicles: kept ones stay, gone ones are freed, new ones assigned."""
        present = {v.vehicle_id for v in vehicles}
        if len(vehicles) > self.config.max_vehicles:   # checked before any slot changes
            raise GraphCapacityError(f'{len(vehicles)} vehicles on the road but graph.max_vehicles = '
                                     f'{self.config.max_vehicles}')
        for vehicle_id in [vid for vid in self._slot_of if vid not in present]:
            self._free.append(self._slot_of.pop(vehicle_id))
        self._free.sort(reverse=True)  # pop() hands out the lowest free slot
        result = []
        for vehicle in vehicles:
            slot = self._slot_of.get(vehicle.vehicle_id)
            if slot is None:
                if not self._free:
                    raise GraphCapacityError(
                        f'{len(vehicles)} vehicles on the road but graph.max_vehicles = '
                        f'{self.config.max_vehicles}')
                slot = self._slot_of[vehicle.vehicle_id] = self._free.pop()
            result.append(slot)
        return result

    def build(self, vehicles: Sequence[VehicleState], snapshot: TrafficSnapshot | None = None) -> TrafficGraph:
        """The graph of one step; ``snapshot``: these vehicles' TrafficSnapshot if the caller has one.

        Input that cannot be encoded raises (GraphInputError, GraphCapacityError) before any
        slot changes."""
        n = self.config.max_vehicles
        lane = np.array([v.lane_index for v in vehicles], dtype=np.int64)
        if len(lane) and (lane.min() < 0 or lane.max() >= self.lane_count):
            raise GraphInputError(f'lane_index {int(lane.min() if lane.min() < 0 else lane.max())} is outside '
                                  f'0..{self.lane_count - 1}')
        rows = np.asarray(self.slots(vehicles), dtype=np.intp)
        features = np.zeros((n, self.num_features), dtype=np.float32)
        adjacency = np.zeros((n, n), dtype=np.uint8)
        cav_mask = np.zeros(n, dtype=bool)
        ids = [''] * n
        if len(vehicles):
            speed = np.array([v.speed for v in vehicles])
            position = np.array([v.position for v in vehicles])
            intention = np.array([v.intention for v in vehicles])
            is_cav = np.array([v.controlled for v in vehicles])
            features[rows, 0] = speed / self.speed_scale
            features[rows, 1] = position / self.road_length
            features[rows, 2 + lane] = 1.0
            features[rows, 5] = intention == INTENTION_LEFT
            features[rows, 6] = intention == INTENTION_RIGHT
            features[rows, 7] = (intention != INTENTION_LEFT) & (intention != INTENTION_RIGHT)
            # Edges among the present vehicles, then scattered into slot order.
            close = np.abs(position[:, None] - position[None, :]) <= self.config.sensing_range
            links = (is_cav[:, None] & is_cav[None, :]) | (close & (is_cav[:, None] ^ is_cav[None, :]))
            np.fill_diagonal(links, True)
            adjacency[np.ix_(rows, rows)] = links
            cav_mask[rows] = is_cav
            if self.config.feature_set == 'relative':
                features[rows, len(PAPER_FEATURES):] = self.relative_features(
                    vehicles, TrafficSnapshot(vehicles) if snapshot is None else snapshot)
            for row, vehicle in zip(rows, vehicles):
                ids[row] = vehicle.vehicle_id
        return TrafficGraph(features, adjacency, cav_mask, tuple(ids))

    def relative_features(self, vehicles: Sequence[VehicleState], snapshot: TrafficSnapshot) -> np.ndarray:
        """(len(vehicles), 4 per lane offset): leader gap, leader's relative speed, follower gap,
        follower's relative speed. Made as Python floats and cast once: writing numpy cells one
        by one was most of it, and np.clip on a scalar cost 2 ms per graph of 40 vehicles."""
        rows = []
        for vehicle in vehicles:
            row: list[float] = []
            speed = vehicle.speed
            for offset in LANE_OFFSETS.values():
                lane = vehicle.lane_index + offset
                if not offset:
                    corridor = vehicle.corridor
                elif vehicle.on_highway and 0 <= lane < self.lane_count:
                    corridor = (HIGHWAY, lane)
                else:
                    row += (0.0, 0.0, 0.0, 0.0)   # no such lane: gaps 0, speeds 0
                    continue
                leader, leader_gap, follower, follower_gap = snapshot.neighbours(
                    corridor, vehicle.position, vehicle.length, exclude=vehicle.vehicle_id)
                row += (min(max(leader_gap, 0.0) / GAP_SCALE, 1.0),
                        min(max((leader.speed - speed) / SPEED_SCALE, -1.0), 1.0) if leader is not None else 0.0,
                        min(max(follower_gap, 0.0) / GAP_SCALE, 1.0),
                        min(max((follower.speed - speed) / SPEED_SCALE, -1.0), 1.0) if follower is not None else 0.0)
            rows.append(row)
        return np.array(rows, dtype=np.float32).reshape(len(vehicles), 4 * len(LANE_OFFSETS))
