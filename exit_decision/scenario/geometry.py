"""Where every lane of the generated network lies along the road (junction lanes included).

Positions are measured from the start of Highway_0; netconvert puts a junction lane of a
few metres between consecutive edges, and it counts. Used by the simulation to report
positions and by anything that needs the road length without running SUMO (graph node).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import sumolib

from exit_decision.config import RoadConfig
from exit_decision.scenario.sumo_inputs import DIVERGES, HIGHWAY_EDGES, build_network
from exit_decision.traffic import VehicleState


@dataclass(frozen=True, slots=True)
class LaneInfo:
    edge_id: str            # reported edge (the edge ahead, for a junction lane)
    lane_index: int         # reported lane index (of the lane ahead, for a junction lane)
    offset: float           # [m] position of the lane's start along the road
    speed_limit: float      # [m/s]


@dataclass(frozen=True)
class RoadGeometry:
    net_file: Path
    lanes: dict[str, LaneInfo]
    diverge_at: dict[str, float]     # [m] position of the end of Highway_0 / Highway_1
    merge_done_at: dict[str, float]  # [m] where the junction after that edge ends (next edge starts)
    road_length: float               # [m] start of Highway_0 to the end of Highway_2
    commit_distance: float           # [m] before a diverge, the lane held picks the exit
    lane_count: int

    def lane_change_exists(self, vehicle: VehicleState, lane_change: int) -> bool:
        """The target lane is on the road, and the vehicle is not where its lane picks its exit."""
        if lane_change == 0:
            return True
        return (vehicle.on_highway and 0 <= vehicle.lane_index + lane_change < self.lane_count
                and not self.no_lane_change_zone(vehicle.position))

    def route_lanes(self, position: float) -> range:
        """The lanes from which the task exit is reached as planned at ``position``: until
        Exit_0's junction ends, every lane but 0 (lane 0 takes Exit_0); from there to Exit_1's
        diverge, lane 0; past it, any lane (the task is decided)."""
        if position < self.merge_done_at['Highway_0']:
            return range(1, self.lane_count)
        if position < self.diverge_at['Highway_1']:
            return range(0, 1)
        return range(self.lane_count)

    def no_lane_change_zone(self, position: float) -> bool:
        """True in the last metres before a diverge and on its junction: no lane changes there
        (the lane held picks the exit; SUMO has no lane changes on junction lanes)."""
        return any(end - self.commit_distance <= position < self.merge_done_at[edge]
                   for edge, end in self.diverge_at.items())

    @classmethod
    def of(cls, road: RoadConfig) -> RoadGeometry:
        net_file = build_network(road)
        net = sumolib.net.readNet(str(net_file), withInternal=True)
        lanes: dict[str, LaneInfo] = {}
        offsets = {'Highway_0': 0.0}
        for edge_id in (*HIGHWAY_EDGES, *DIVERGES.values()):
            edge = net.getEdge(edge_id)
            start = offsets[edge_id]
            for lane in edge.getLanes():
                lanes[lane.getID()] = LaneInfo(edge_id, lane.getIndex(), start, lane.getSpeed())
            junction_start = start + edge.getLength()
            for connections in edge.getOutgoing().values():
                for connection in connections:
                    via = net.getLane(connection.getViaLaneID())
                    to_lane = connection.getToLane()
                    lanes[via.getID()] = LaneInfo(to_lane.getEdge().getID(), to_lane.getIndex(),
                                                  junction_start, via.getSpeed())
                    offsets[to_lane.getEdge().getID()] = junction_start + via.getLength()
        ends = {edge: offsets[edge] + net.getEdge(edge).getLength() for edge in HIGHWAY_EDGES}
        following = dict(zip(HIGHWAY_EDGES, HIGHWAY_EDGES[1:]))
        return cls(net_file, lanes, diverge_at={edge: ends[edge] for edge in DIVERGES},
                   merge_done_at={edge: offsets[following[edge]] for edge in DIVERGES},
                   road_length=ends['Highway_2'], commit_distance=road.diverge_commit_distance,
                   lane_count=road.lane_count)
