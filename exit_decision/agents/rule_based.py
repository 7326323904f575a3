"""A rule-based CAV driver in the policy's own action space: the demonstrator and a baseline.

Lane plan: before the first exit, hold lane 1 (out of lane 0, which would take the first exit,
and one change from lane 0); after the first exit's junction, move right into lane 0 before the
target exit's diverge. Speed: IDM towards the lane's limit, slowing to the ramp's limit before
the target exit with a comfortable deceleration; while waiting for a gap to the right, it drops back a little.
Every choice is made under the same shield as the learned policy, and quantised to the grid.
"""
from __future__ import annotations

import math

import numpy as np

from exit_decision.actions import ActionGrid
from exit_decision.agents.shield import Decision, Shield
from exit_decision.config import RuleBasedConfig
from exit_decision.graph import TrafficGraph
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import HIGHWAY, CavCommand, TrafficSnapshot, VehicleState



class RuleBasedDriver:
    name = 'rule_based'

    def __init__(self, grid: ActionGrid, shield: Shield, geometry: RoadGeometry,
                 ramp_speed_limit: float, parameters: RuleBasedConfig):
        self.grid = grid
        self.shield = shield
        self.geometry = geometry
        self.ramp_speed_limit = ramp_speed_limit
        self.parameters = parameters

    def target_lane(self, vehicle: VehicleState) -> int:
        """The route lane nearest to lane 0 (before the first exit: lane 1, one change from the
        exit lane to come); past the target exit's diverge the lane held (the task is decided)."""
        if vehicle.position < self.geometry.target_exit.diverge_at:
            return min(self.geometry.route_lanes(vehicle.position))
        return vehicle.lane_index

    def desired_speed(self, vehicle: VehicleState) -> float:
        limit = vehicle.lane_speed_limit
        first, target = self.geometry.first_exit, self.geometry.target_exit
        if vehicle.on_highway and first.merge_done_at <= vehicle.position < target.diverge_at:
            # slow to the ramp's limit by the target exit's diverge, braking comfortably
            distance = max(target.diverge_at - vehicle.position, 0.0)
            limit = min(limit, math.sqrt(self.ramp_speed_limit ** 2
                                         + 2 * self.parameters.comfortable_braking * distance))
        return limit

    def idm(self, speed: float, desired: float, gap: float | None, leader_speed: float) -> float:
        """IDM acceleration; ``gap`` None means no leader."""
        p = self.parameters
        free = 1.0 - (speed / desired) ** 4 if desired > 0 else -1.0
        if p.overspeed_time is not None and speed > desired:
            # above the desired speed (the ramp's limit ahead, or on the ramp): IDM's free term
            # lags the falling limit and then brakes hard at once; close the excess over
            # ``overspeed_time`` instead, at most comfortably
            free = -min((speed - desired) / p.overspeed_time, p.comfortable_braking) / p.max_acceleration
        if gap is None:
            return p.max_acceleration * free
        wanted = p.standstill_gap + speed * p.time_headway + speed * (speed - leader_speed) / (
            2 * math.sqrt(p.max_acceleration * p.comfortable_braking))
        # IDM over-brakes on short gaps; beyond the firm braking the shield decides how hard
        return max(p.max_acceleration * (free - (max(wanted, 0.0) / max(gap, 0.1)) ** 2), -p.firm_braking)

    def acceleration(self, vehicle: VehicleState, snapshot: TrafficSnapshot, lane: int | None = None) -> float:
        """IDM acceleration of the vehicle behind its leader in ``lane`` (default: its own)."""
        ahead = self.shield.leader(vehicle, vehicle.lane_index if lane is None else lane, snapshot)
        leader = ahead.leader
        return self.idm(vehicle.speed, self.desired_speed(vehicle), ahead.leader_gap if leader else None,
                        leader.speed if leader else 0.0)

    def urgency(self, vehicle: VehicleState) -> float:
        """0 far from the diverge where the lane must be reached, rising to 1 at its last metres."""
        first = self.geometry.first_exit
        deadline = first if vehicle.position < first.merge_done_at else self.geometry.target_exit
        remaining = deadline.diverge_at - self.geometry.commit_distance - vehicle.position
        return float(np.clip(1.0 - remaining / self.parameters.urgency_distance, 0.0, 1.0))

    def change_is_acceptable(self, vehicle: VehicleState, lane_change: int, snapshot: TrafficSnapshot) -> bool:
        """MOBIL's safety criterion: after the change neither the CAV nor its new follower has
        to brake harder than the accepted braking, which grows from the comfortable one to the
        urgent one as the diverge nears."""
        lane = vehicle.lane_index + lane_change
        p = self.parameters
        limit = -(p.comfortable_braking + (p.urgent_braking - p.comfortable_braking) * self.urgency(vehicle))
        if self.acceleration(vehicle, snapshot, lane) < limit:
            return False
        around = snapshot.neighbours((HIGHWAY, lane), vehicle.position, vehicle.length,
                                     exclude=vehicle.vehicle_id)
        follower = around.follower
        if follower is None:
            return True
        if p.connected_cavs and follower.controlled \
                and not self.follower_keeps_out_of_hard_braking(vehicle, follower, around.follower_gap):
            return False
        return self.idm(follower.speed, follower.lane_speed_limit, around.follower_gap, vehicle.speed) >= limit

    def follower_keeps_out_of_hard_braking(self, vehicle: VehicleState, follower: VehicleState,
                                           gap: float) -> bool:
        """Would a CAV follower, with this CAV ``gap`` metres in front of it, still have an
        acceleration above the hard-braking threshold that its shield's stop-capable mask
        allows? (Its shield decides how hard it brakes; IDM's estimate below is capped at the
        firm braking and so lets any cut-in pass near the deadline: measured, most of the CAVs'
        hard brakings were such cut-ins in front of other CAVs.)"""
        shield = self.shield
        allowed = shield.stop_capable(shield.ego_motion(follower.speed), gap, vehicle.speed)
        return bool((allowed & shield.not_hard_braking).any())

    def preferred(self, vehicle: VehicleState, snapshot: TrafficSnapshot,
                  target: int | None = None) -> tuple[int, float]:
        """(lane change, acceleration) the rules want, before any mask, towards the ``target``
        lane (default: the route's, ``target_lane``)."""
        target = self.target_lane(vehicle) if target is None else target
        lane_change = int(np.sign(target - vehicle.lane_index)) if vehicle.on_highway else 0
        if lane_change and self.change_is_acceptable(vehicle, lane_change, snapshot):
            return lane_change, min(self.acceleration(vehicle, snapshot),
                                    self.acceleration(vehicle, snapshot, vehicle.lane_index + lane_change))
        accel = self.acceleration(vehicle, snapshot)
        if lane_change:
            accel = self.gap_search(vehicle, lane_change, snapshot, accel)
        elif self.parameters.connected_cavs:
            accel = self.make_room(vehicle, snapshot, accel)
        return 0, accel

    def make_room(self, vehicle: VehicleState, snapshot: TrafficSnapshot, accel: float) -> float:
        """Connected CAVs make room for each other: a CAV that keeps its lane follows, as a
        virtual leader, a CAV ahead of it in a next lane (within ``make_room_distance``) whose
        route needs this lane, so the gap the merger needs opens behind it (the merger holds
        its own lane's speed meanwhile: ``gap_search``). IDM behind a virtual leader never asks
        for less than the merger's speed, so no chain of CAVs slows itself down."""
        if not vehicle.on_highway:
            return accel
        p = self.parameters
        for lane in (vehicle.lane_index - 1, vehicle.lane_index + 1):
            if not 0 <= lane < self.geometry.lane_count:
                continue
            merger = snapshot.neighbours((HIGHWAY, lane), vehicle.position, vehicle.length,
                                         exclude=vehicle.vehicle_id).leader
            if (merger is not None and merger.controlled and merger.on_highway
                    and 0.0 < merger.position - vehicle.position <= p.make_room_distance
                    and self.target_lane(merger) == vehicle.lane_index):
                gap = merger.position - merger.length - vehicle.position
                accel = min(accel, self.idm(vehicle.speed, self.desired_speed(vehicle), gap, merger.speed))
        return accel

    def gap_search(self, vehicle: VehicleState, lane_change: int, snapshot: TrafficSnapshot,
                   accel: float) -> float:
        """While a lane change is blocked: drop behind the nearer vehicle of the target lane
        (a little slower than it), or pull ahead of it (a little faster) when it is behind
        and the own lane's IDM allows that speed in full. Otherwise it drops back: a CAV that
        half pulls ahead rides alongside a follower that slows with it (near the exit, where
        both slow for the ramp), and the change never comes (measured: 16 of 300 CAVs missed
        the target exit that way on the demonstration seeds, 0 with this rule)."""
        p = self.parameters
        around = snapshot.neighbours((HIGHWAY, vehicle.lane_index + lane_change), vehicle.position,
                                     vehicle.length, exclude=vehicle.vehicle_id)
        if around.leader is None and around.follower is None:
            return accel
        to_speed = lambda goal: float(np.clip(goal - vehicle.speed, -p.firm_braking, p.max_acceleration))  # noqa: E731
        if around.leader is not None and around.leader_gap <= around.follower_gap:
            return min(accel, to_speed(around.leader.speed - p.gap_search_speed))
        if p.connected_cavs and around.follower.controlled:
            return accel   # a CAV follower makes room (``make_room``): hold the own lane's speed
        pull_ahead = to_speed(around.follower.speed + p.gap_search_speed)
        if accel >= pull_ahead:
            return pull_ahead
        return min(accel, to_speed(around.follower.speed - p.gap_search_speed))

    def choose(self, vehicle: VehicleState, mask: np.ndarray, snapshot: TrafficSnapshot) -> int:
        """Best allowed action: the wanted lane change if allowed, else keep lane; the closest
        allowed acceleration not above the wanted one, else the smallest allowed above it."""
        grid = self.grid
        lane_change, wanted = self.preferred(vehicle, snapshot)
        if lane_change and not (mask & grid.rows(lane_change)).any():
            # the shield refuses the change the rules accepted: keep lane and look for a gap
            wanted = self.gap_search(vehicle, lane_change, snapshot, self.acceleration(vehicle, snapshot))
            lane_change = 0
        for change in ([lane_change, 0] if lane_change else [0]):
            rows = mask & grid.rows(change)
            if not rows.any():
                continue
            below = rows & (grid.acceleration_of <= wanted + 1e-9)
            pool = below if below.any() else rows
            candidates = np.flatnonzero(pool)
            distance = np.abs(grid.acceleration_of[candidates] - wanted)
            return int(candidates[np.argmin(distance)])
        return int(np.flatnonzero(mask)[0])

    def command(self, vehicle: VehicleState, mask: np.ndarray, snapshot: TrafficSnapshot,
                target: int | None = None) -> CavCommand:
        """The rules' command off the grid (the options' low level): the wanted lane change if
        the mask allows it, and the wanted acceleration clipped into the mask's allowed range for
        that lane. (A lane's allowed accelerations are an interval: every layer of the shield
        allows all accelerations below a bound, or all above the hard-braking threshold.) Not
        rounding down to the grid is worth most of the efficiency row the grid driver loses to
        SUMO's drivers (docs/design.md, "Rule-based driver")."""
        grid = self.grid
        lane_change, wanted = self.preferred(vehicle, snapshot, target)
        if lane_change and not (mask & grid.rows(lane_change)).any():
            wanted = self.gap_search(vehicle, lane_change, snapshot, self.acceleration(vehicle, snapshot))
            lane_change = 0
        if not (mask & grid.rows(lane_change)).any():
            lane_change = int(grid.lane_change_of[np.flatnonzero(mask)[0]])
        allowed = grid.acceleration_of[mask & grid.rows(lane_change)]
        return CavCommand(lane_change, float(np.clip(wanted, allowed.min(), allowed.max())))

    def commands(self, graph: TrafficGraph, snapshot: TrafficSnapshot) -> dict[str, CavCommand]:
        """Every CAV's ``command`` under the shield."""
        return shielded_commands(self.shield, snapshot, graph.cav_ids(),
                                 lambda vehicle, mask: self.command(vehicle, mask, snapshot))

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot) -> Decision:
        cav_ids = graph.cav_ids()
        return self.shield.decide(
            snapshot, cav_ids, lambda vehicle, mask: self.choose(vehicle, mask, snapshot),
            preferred=lambda vehicle: self.grid.index(*self.preferred(vehicle, snapshot)))


def shielded_commands(shield: Shield, snapshot: TrafficSnapshot, cav_ids, command_of) -> dict[str, CavCommand]:
    """Off-grid commands of CAVs under the shield, front to back with gap reservation:
    ``command_of(vehicle, mask)`` gives a command within the mask's range (``command``); the
    shield reserves the gap of the grid action nearest to it."""
    grid = shield.grid
    chosen: dict[str, CavCommand] = {}

    def choose(vehicle: VehicleState, mask: np.ndarray) -> int:
        command = chosen[vehicle.vehicle_id] = command_of(vehicle, mask)
        rows = np.flatnonzero(mask & grid.rows(command.lane_change))
        return int(rows[np.argmin(np.abs(grid.acceleration_of[rows] - command.acceleration))])

    shield.decide(snapshot, cav_ids, choose)
    return chosen
