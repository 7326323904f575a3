"""Where every lane of the generated network lies along the road (junction lanes included).

Positions are measured from the start of the first highway section; netconvert puts a
junction lane of a few metres between consecutive edges, and it counts. Used by the
simulation to report positions and by anything that needs the road length without running
SUMO (graph node). Edges are asked for by role (``first_exit``, ``target_exit``,
``sections``): their names are the scenario config's.
"""
from __future__ import annotations

import math
import itertools
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import sumolib

from exit_decision.config import RoadConfig
from exit_decision.scenario.sumo_inputs import build_network, diverges
from exit_decision.traffic import VehicleState


@dataclass(frozen=True, slots=True)
class LaneInfo:
    edge_id: str            # reported edge (the edge ahead, for a junction lane)
    lane_index: int         # reported lane index (of the lane ahead, for a junction lane)
    offset: float           # [m] position of the lane's start along the road
    speed_limit: float      # [m/s]
    on_highway: bool        # on a highway section (or the junction into one), not on a ramp


@dataclass(frozen=True, slots=True)
class Exit:
    """A ramp off lane 0 at the end of a highway section."""
    ramp: str               # the ramp's edge id
    section: str            # the highway section it leaves at the end of
    diverge_at: float       # [m] position of the end of that section
    merge_done_at: float    # [m] where the junction after that section ends (the next section starts)
    direction: tuple[float, float]   # unit vector of the ramp in the network's plane (x along the road)


def direction(shape: list[tuple[float, float]]) -> tuple[float, float]:
    """Unit vector from a lane shape's first point to its last."""
    (x0, y0), *_, (x1, y1) = shape
    norm = math.hypot(x1 - x0, y1 - y0)
    return (x1 - x0) / norm, (y1 - y0) / norm


@dataclass(frozen=True)
class RoadGeometry:
    net_file: Path
    lanes: dict[str, LaneInfo]
    sections: tuple[str, ...]        # highway section edge ids, upstream to downstream
    first_exit: Exit                 # the ramp off the first section (HV3's exit)
    target_exit: Exit                # the ramp off the second section: every CAV's task
    road_length: float               # [m] start of the first section to the end of the last
    commit_distance: float           # [m] before a diverge, the lane held picks the exit
    lane_count: int

    @cached_property
    def exits(self) -> dict[str, Exit]:
        """Every exit, by the highway section it leaves."""
        return {exit_.section: exit_ for exit_ in (self.first_exit, self.target_exit)}

    @cached_property
    def diverge_at(self) -> dict[str, float]:
        """[m] position of the end of each highway section that has an exit, by section."""
        return {section: exit_.diverge_at for section, exit_ in self.exits.items()}

    @cached_property
    def merge_done_at(self) -> dict[str, float]:
        """[m] where the junction after each section with an exit ends, by section."""
        return {section: exit_.merge_done_at for section, exit_ in self.exits.items()}

    def lane_change_exists(self, vehicle: VehicleState, lane_change: int) -> bool:
        """The target lane is on the road, and the vehicle is not where its lane picks its exit."""
        if lane_change == 0:
            return True
        return (vehicle.on_highway and 0 <= vehicle.lane_index + lane_change < self.lane_count
                and not self.no_lane_change_zone(vehicle.position))

    def route_lanes(self, position: float) -> range:
        """The lanes from which the target exit is reached as planned at ``position``: until
        the first exit's junction ends, every lane but 0 (lane 0 takes the first exit); from
        there to the target exit's diverge, lane 0; past it, any lane (the task is decided)."""
        if position < self.first_exit.merge_done_at:
            return range(1, self.lane_count)
        if position < self.target_exit.diverge_at:
            return range(0, 1)
        return range(self.lane_count)

    def no_lane_change_zone(self, position: float) -> bool:
        """True in the last metres before a diverge and on its junction: no lane changes there
        (the lane held picks the exit; SUMO has no lane changes on junction lanes)."""
        return any(exit_.diverge_at - self.commit_distance <= position < exit_.merge_done_at
                   for exit_ in (self.first_exit, self.target_exit))

    @classmethod
    def of(cls, road: RoadConfig) -> RoadGeometry:
        net_file = build_network(road)
        net = sumolib.net.readNet(str(net_file), withInternal=True)
        sections = road.names.sections
        ramps = diverges(road.names)
        lanes: dict[str, LaneInfo] = {}
        offsets = {sections[0]: 0.0}
        for edge_id in (*sections, *ramps.values()):
            edge = net.getEdge(edge_id)
            start = offsets[edge_id]
            for lane in edge.getLanes():
                lanes[lane.getID()] = LaneInfo(edge_id, lane.getIndex(), start, lane.getSpeed(),
                                               edge_id in sections)
            junction_start = start + edge.getLength()
            for connections in edge.getOutgoing().values():
                for connection in connections:
                    via = net.getLane(connection.getViaLaneID())
                    to_lane = connection.getToLane()
                    to_edge = to_lane.getEdge().getID()
                    lanes[via.getID()] = LaneInfo(to_edge, to_lane.getIndex(), junction_start, via.getSpeed(),
                                                  to_edge in sections)
                    offsets[to_edge] = junction_start + via.getLength()
        ends = {edge: offsets[edge] + net.getEdge(edge).getLength() for edge in sections}
        following = dict(itertools.pairwise(sections))
        first_exit, target_exit = (Exit(ramp, section, ends[section], offsets[following[section]],
                                        direction(net.getLane(f'{ramp}_0').getShape()))
                                   for section, ramp in ramps.items())
        return cls(net_file, lanes, sections, first_exit, target_exit, road_length=ends[sections[-1]],
                   commit_distance=road.diverge_commit_distance, lane_count=road.lane_count)
