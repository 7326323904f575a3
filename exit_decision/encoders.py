"""State encoders: what each method's network sees of the traffic (issue 11; docs/design.md,
"The other papers' methods").

Every encoder maps the graph of ``exit_decision.graph`` (its slots, CAV mask and adjacency
unchanged) and the step's vehicle states to per-row features, so replay, the agent loop, the
policy and the decision node treat every method alike; only the CAV rows are filled.

- ``graph``: the graph builder's features as configured (paper 000; ``relative`` by default).
- ``graph_paper``: the paper feature set only (speed, position, lane and intention one-hots;
  paper 001's 8 inputs).
- ``grid`` (paper 002, after Bai et al.): each highway lane cut into ``GRID_CELLS`` cells of
  an average car length around the ego vehicle (5 behind, 5 ahead); per cell whether a
  vehicle occupies it (the ego's own cell: -1, so it knows its lane) and that vehicle's
  speed / lane limit; 3 lanes x 10 cells x 2 = 60 values.
- ``nearest`` (paper 003): the ego's speed, then the ``NEAREST_COUNT`` nearest vehicles
  (exists, dx / 50 m, lanes apart / lane count, dv / 10 m/s, its lane-change intention as the
  lateral motion our states have), nearest first: 1 + 6 x 5 = 31 values.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from exit_decision.graph import GAP_SCALE, PAPER_FEATURES, SPEED_SCALE, TrafficGraph
from exit_decision.scenario.sumo_inputs import LANE_WIDTH   # the distance that ranks the nearest vehicles
from exit_decision.traffic import INTENTION_LEFT, INTENTION_RIGHT, TrafficSnapshot, VehicleState

ENCODERS = ('graph', 'graph_paper', 'grid', 'nearest')
GRID_CELLS = 10            # paper 002: a span of 10 cells
GRID_CELL_LENGTH = 5.0     # [m] the average car length (paper 002)
NEAREST_COUNT = 6          # paper 003
NEAREST_VALUES = 5         # exists, dx, dy, dvx, dvy


class StateEncoder:
    """The features of one method: ``encode(graph, snapshot)`` -> the graph with its rows'
    features replaced (the identity for ``graph``)."""

    def __init__(self, name: str, graph_features: int, lane_count: int, speed_limit: float):
        if name not in ENCODERS:
            raise ValueError(f'unknown state encoder {name!r}; known: {", ".join(ENCODERS)}')
        self.name, self.lane_count, self.speed_limit = name, lane_count, speed_limit
        #: what makes this encoder again (a checkpoint's metadata keeps it)
        self.settings = {'name': name, 'graph_features': graph_features, 'lane_count': lane_count,
                         'speed_limit': speed_limit}
        self.num_features = {'graph': graph_features, 'graph_paper': len(PAPER_FEATURES),
                             'grid': lane_count * GRID_CELLS * 2,
                             'nearest': 1 + NEAREST_COUNT * NEAREST_VALUES}[name]

    def encode(self, graph: TrafficGraph, snapshot: TrafficSnapshot) -> TrafficGraph:
        if self.name == 'graph':
            return graph
        if self.name == 'graph_paper':
            return replace(graph, features=np.ascontiguousarray(graph.features[:, :len(PAPER_FEATURES)]))
        features = np.zeros((graph.num_nodes, self.num_features), np.float32)
        row_features = self.grid if self.name == 'grid' else self.nearest
        for row in graph.cav_rows():
            features[row] = row_features(snapshot.by_id[graph.vehicle_ids[row]], snapshot)
        return replace(graph, features=features)

    def grid(self, ego: VehicleState, snapshot: TrafficSnapshot) -> np.ndarray:
        cells = np.zeros((self.lane_count, GRID_CELLS, 2), np.float32)
        half = GRID_CELLS // 2
        for other in snapshot.vehicles:
            if ego.on_highway:   # the highway's lanes; on a ramp, its one corridor as lane 0
                lane = other.lane_index if other.on_highway else None
            else:
                lane = 0 if other.corridor == ego.corridor else None
            if lane is None or not 0 <= lane < self.lane_count:
                continue
            cell = math.floor((other.position - ego.position) / GRID_CELL_LENGTH + 0.5) + half
            if 0 <= cell < GRID_CELLS:
                occupied = -1.0 if other.vehicle_id == ego.vehicle_id else 1.0
                if cells[lane, cell, 0] != -1.0:   # the ego's own mark wins its cell
                    cells[lane, cell] = occupied, other.speed / self.speed_limit
        return cells.ravel()

    def nearest(self, ego: VehicleState, snapshot: TrafficSnapshot) -> np.ndarray:
        out = np.zeros(1 + NEAREST_COUNT * NEAREST_VALUES, np.float32)
        out[0] = ego.speed / self.speed_limit
        ranked = []
        for other in snapshot.vehicles:
            if other.vehicle_id == ego.vehicle_id:
                continue
            if ego.on_highway and other.on_highway:
                lanes_apart = other.lane_index - ego.lane_index
            elif other.corridor == ego.corridor:
                lanes_apart = 0
            else:
                continue
            dx = other.position - ego.position
            ranked.append((math.hypot(dx, LANE_WIDTH * lanes_apart), dx, lanes_apart, other))
        ranked.sort(key=lambda entry: entry[0])
        for i, (_, dx, lanes_apart, other) in enumerate(ranked[:NEAREST_COUNT]):
            lateral = {INTENTION_LEFT: 1.0, INTENTION_RIGHT: -1.0}.get(other.intention, 0.0)
            out[1 + NEAREST_VALUES * i:1 + NEAREST_VALUES * (i + 1)] = (
                1.0, max(-1.0, min(dx / GAP_SCALE, 1.0)), lanes_apart / self.lane_count,
                max(-1.0, min((other.speed - ego.speed) / SPEED_SCALE, 1.0)), lateral)
        return out
