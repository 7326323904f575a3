"""Action masks that are also the runtime safety shield (ours; docs/design.md, "Safety shield").

The same masks run in training, evaluation and the decision node, from vehicle states only.
For one decision, CAVs are taken front to back; each gets a mask over the action grid and
chooses (``Shield.decide``), and a chosen lane change reserves its gap: the CAV is added as
a virtual vehicle in the target lane for the CAVs that decide after it.

Masks (each but the first a config switch):
- lanes that do not exist, and lane changes where the lane held picks the exit;
- a lane change into a gap with a vehicle too close ahead or behind, or one that would need
  braking at the hard-braking threshold (``lane_gap``);
- two CAVs claiming the same gap in one decision (``gap_reservation``);
- an acceleration after which the CAV, holding it for one decision interval, could no longer
  stop behind its leader if the leader braked at its maximum (``stop_capable``);
- braking harder than the threshold with a human follower close behind (``human_follower_braking``).
If every action is masked, the strongest keep-lane braking is allowed (the safest left).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from exit_decision.actions import ActionGrid
from exit_decision.config import ProjectConfig, ShieldConfig
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import HIGHWAY, Neighbours, TrafficSnapshot, VehicleState

#: chooses an action index for a vehicle, given its mask over the grid
Chooser = Callable[[VehicleState, np.ndarray], int]


@dataclass(frozen=True, slots=True)
class Decision:
    actions: dict[str, int]              # vehicle id -> chosen action index
    masks: dict[str, np.ndarray]         # vehicle id -> the mask it chose under
    refused: dict[str, int]              # vehicle id -> its unmasked first choice, where the mask refused it

    @property
    def overridden(self) -> int:
        """How many CAVs the shield overrode."""
        return len(self.refused)


class Shield:
    def __init__(self, config: ShieldConfig, grid: ActionGrid, geometry: RoadGeometry, decision_time: float):
        self.config = config
        self.grid = grid
        self.geometry = geometry
        self.horizon = decision_time            # [s] an action is held this long
        self.fallback = grid.index(0, grid.accelerations.min())
        self.not_hard_braking = grid.accelerations > config.hard_braking   # per acceleration of the grid
        a, t = grid.accelerations, decision_time
        #: what ``ego_motion`` needs of the grid: a t, 2 max(-a, tiny) (a stop within the interval
        #: takes v^2 / that), a t^2 / 2 (each as the formula computes it, so the masks are exact)
        self.grid_motion = (a * t, 2 * np.maximum(-a, 1e-9), 0.5 * a * t * t)

    @classmethod
    def of(cls, config: ProjectConfig, grid: ActionGrid, geometry: RoadGeometry) -> Shield:
        """The shield of a project config: an action is held for one decision interval."""
        return cls(config.env.shield, grid, geometry, config.env.decision_interval * config.scenario.step_length)

    def bare(self) -> Shield:
        """This shield with every switchable mask off: only lanes that exist (what a method run
        as published drives with)."""
        layers = {'lane_gap': False, 'gap_reservation': False, 'stop_capable': False, 'human_follower_braking': False}
        return Shield(self.config.model_copy(update=layers), self.grid, self.geometry, self.horizon)

    # --- one vehicle -----------------------------------------------------------------------

    @staticmethod
    def around(vehicle: VehicleState, lane: int, snapshot: TrafficSnapshot) -> Neighbours:
        """The vehicle's neighbours in highway ``lane`` (on a ramp: in its ramp)."""
        corridor = (HIGHWAY, lane) if vehicle.on_highway else vehicle.corridor
        return snapshot.neighbours(corridor, vehicle.position, vehicle.length, exclude=vehicle.vehicle_id)

    def leader(self, vehicle: VehicleState, lane: int, snapshot: TrafficSnapshot,
               around: Neighbours | None = None) -> Neighbours:
        """Closest vehicle ahead in ``lane`` (a ramp in lane 0 before its diverge counts too);
        ``around``: the vehicle's ``around`` in that lane, if the caller has it already."""
        around = self.around(vehicle, lane, snapshot) if around is None else around
        exit_ = self.geometry.exits.get(vehicle.edge_id) if vehicle.on_highway and lane == 0 else None
        if exit_ is None:
            return around
        ramp = snapshot.neighbours((exit_.ramp, 0), vehicle.position, vehicle.length, exclude=vehicle.vehicle_id)
        return ramp if ramp.leader_gap < around.leader_gap else around

    def ego_motion(self, speed: float) -> tuple[np.ndarray, np.ndarray]:
        """Per acceleration of the grid, for a CAV at ``speed`` holding it one decision
        interval: the distance it travels and the braking distance it then needs at its
        maximum braking. (The part of ``stop_capable`` that does not depend on the lane: one
        mask computes it once for its three lanes.)"""
        t, (a_t, two_decelerations, half_a_t2) = self.horizon, self.grid_motion
        v = speed
        after = v + a_t
        travel = np.where(after < 0, v * v / two_decelerations, v * t + half_a_t2)
        speed_after = np.maximum(after, 0.0)
        return travel, speed_after ** 2 / (2 * self.config.ego_max_braking)

    def stop_capable(self, motion: tuple[np.ndarray, np.ndarray], gap: float, leader_speed: float) -> np.ndarray:
        """Per acceleration of the grid: can the CAV (its ``ego_motion``) still stop behind a
        leader braking at its maximum, after holding that acceleration for one decision interval?"""
        c, t = self.config, self.horizon
        travel, braking_distance = motion
        b = c.leader_max_braking
        leader_travel = leader_speed * leader_speed / (2 * b) if leader_speed < b * t else \
            leader_speed * t - 0.5 * b * t * t
        leader_after = max(leader_speed - b * t, 0.0)
        gap_after = gap + leader_travel - travel
        needed = braking_distance - leader_after ** 2 / (2 * b) + c.stop_margin
        return gap_after >= needed

    def mask(self, vehicle: VehicleState, snapshot: TrafficSnapshot) -> np.ndarray:
        """(A,) bool: the actions this CAV may take now."""
        c, grid = self.config, self.grid
        allowed = np.zeros(grid.size, dtype=bool)
        motion = self.ego_motion(vehicle.speed) if c.stop_capable else None
        for lane_change in grid.lane_changes:
            if not self.geometry.lane_change_exists(vehicle, lane_change):
                continue
            lane = vehicle.lane_index + lane_change
            ok = True   # every acceleration of the lane, until a layer narrows it
            around = self.around(vehicle, lane, snapshot)
            if lane_change and c.lane_gap:
                closing = max(around.follower.speed - vehicle.speed, 0.0) if around.follower else 0.0
                if (around.leader_gap < c.gap_front
                        or around.follower_gap < c.gap_back + c.gap_back_time * closing):
                    continue
                ok = ok & self.not_hard_braking   # a gap that needs hard braking is too small
            if c.stop_capable:
                ahead = self.leader(vehicle, lane, snapshot, around)
                if ahead.leader is not None:
                    ok = ok & self.stop_capable(motion, ahead.leader_gap, ahead.leader.speed)
            if c.human_follower_braking and around.follower is not None \
                    and not around.follower.controlled and around.follower_gap < c.human_follower_distance:
                ok = ok & self.not_hard_braking
            allowed[grid.rows(lane_change)] = ok
        if not allowed.any():
            allowed[self.fallback] = True
        return allowed

    # --- a decision for all CAVs ---------------------------------------------------------------

    def decide(self, snapshot: TrafficSnapshot, cav_ids: Sequence[str], choose: Chooser,
               preferred: Callable[[VehicleState], int] | None = None,
               restrict: Callable[[VehicleState, np.ndarray], np.ndarray] | None = None) -> Decision:
        """Masks and choices for the given CAVs, front to back, reserving chosen gaps.

        ``preferred`` (optional) is the choice without masks, to count overrides; ``restrict``
        (optional) narrows a CAV's mask further (the lane planner's route), never to nothing."""
        present = [snapshot.by_id[vid] for vid in cav_ids]
        actions, masks, refused = {}, {}, {}
        for vehicle in sorted(present, key=lambda v: -v.position):
            mask = self.mask(vehicle, snapshot)
            if restrict is not None:
                mask = restrict(vehicle, mask)
            action = choose(vehicle, mask)
            if not mask[action]:
                raise ValueError(f'{vehicle.vehicle_id}: the chooser picked masked action {action}')
            first_choice = preferred(vehicle) if preferred is not None else action
            if not mask[first_choice]:
                refused[vehicle.vehicle_id] = first_choice
            actions[vehicle.vehicle_id], masks[vehicle.vehicle_id] = action, mask
            lane_change = int(self.grid.lane_change_of[action])
            if lane_change and self.config.gap_reservation:
                snapshot = snapshot.with_vehicle(dataclasses.replace(
                    vehicle, vehicle_id=f'{vehicle.vehicle_id}#reserved',
                    lane_index=vehicle.lane_index + lane_change))
        return Decision(actions, masks, refused)
