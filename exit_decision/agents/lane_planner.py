"""The lane planner: owns the route-critical lane changes of CAVs driven by a learned policy.

A CAV on a lane of its route (``RoadGeometry.route_lanes``) is the policy's: it chooses its
acceleration and its lane changes, but not a change that leaves the route. A CAV off its
route (it entered in lane 0 before the first exit, or is not yet in lane 0 before the target
exit) is driven by the rule-based driver's lane plan and gap search until it is back on it.
Why: the learned policies' whole return gap to the teacher was missed exits, made by
deadline-critical lane choices (riding beside a gap instead of dropping back, a change into
the exit lane of the first exit) that the reward cannot tell apart from style
(docs/design.md, "Learning").
"""
from __future__ import annotations

import numpy as np

from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.agents.shield import Shield
from exit_decision.config import ProjectConfig
from exit_decision.traffic import TrafficSnapshot, VehicleState


class LanePlanner:
    def __init__(self, driver: RuleBasedDriver):
        self.driver = driver
        self.geometry = driver.geometry
        self.grid = driver.grid

    @classmethod
    def of(cls, config: ProjectConfig, shield: Shield) -> LanePlanner | None:
        """The planner of a project config (env.yaml ``lane_planner``), None when turned off."""
        if not config.env.lane_planner:
            return None
        return cls(RuleBasedDriver(shield.grid, shield, shield.geometry, config.scenario.road.ramp_speed_limit,
                                   config.env.rule_based))

    def on_route(self, vehicle: VehicleState, lane: int | None = None) -> bool:
        """Is ``lane`` (default: the vehicle's own) a route lane where the vehicle is?"""
        if not vehicle.on_highway:
            return True
        return (vehicle.lane_index if lane is None else lane) in self.geometry.route_lanes(vehicle.position)

    def restrict(self, vehicle: VehicleState, mask: np.ndarray) -> np.ndarray:
        """The shield's mask without lane changes that leave the route (for a CAV on it)."""
        if not vehicle.on_highway or not self.on_route(vehicle):
            return mask
        lanes = self.geometry.route_lanes(vehicle.position)
        kept = mask.copy()
        for change in self.grid.lane_changes:
            if vehicle.lane_index + change not in lanes:
                kept[self.grid.rows(change)] = False
        return kept if kept.any() else mask

    def choose(self, vehicle: VehicleState, mask: np.ndarray, snapshot: TrafficSnapshot) -> int | None:
        """The planner's action for a CAV off its route, None for one the policy decides."""
        return None if self.on_route(vehicle) else self.driver.choose(vehicle, mask, snapshot)
