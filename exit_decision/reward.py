"""The reward function matrix of paper 000 (Section 4; SPEC section 5) and the baseline reward.

r = tr(A_k1 A_k2 A_r^T): A_k1 = diag(k_result, k_efficiency, k_comfort, k_safety) (the mode's
decision weights), A_k2 = [[k_iI, k_iP]] (incentive / punishment weights, the incentive
ones dynamic, eq. 20), A_r = [[r_iI, r_iP]] (the sub-rewards of the step, each divided by
the variant's scale). The ``literal`` variant is the paper as written; ``bounded`` caps
every exponent and the lane-change count (ours: the literal terms reach 1e10).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from exit_decision.config import BaselineRewardConfig, MatrixRewardConfig, ModeConfig
from exit_decision.traffic import StepResult, TrafficSnapshot, VehicleState

ROWS = ('result', 'efficiency', 'comfort', 'safety')
EXIT_TASK = 'Exit_1'
SAFETY_TIME_CAP = 10.0      # [s] time gaps longer than this count as 10 s
SAFETY_THRESHOLD = 4.0      # [s] below: the hazard regions of the driving hazard diagram
E2 = math.exp(2.0)


@dataclass(frozen=True, slots=True)
class StepRewardInputs:
    """What one simulation step contributes to the reward."""
    step: StepResult
    snapshot: TrafficSnapshot
    recent_lane_changes: int    # m: lane changes of all vehicles in the last 0.5 s


@dataclass(frozen=True, slots=True)
class RewardBreakdown:
    total: float
    sub_rewards: np.ndarray     # (4, 2) raw (unscaled) [incentive, punishment] per row
    weights: np.ndarray         # (4, 2) A_k2 as used (after the dynamic weights)


class MatrixReward:
    """Reward function matrix for one decision mode."""

    def __init__(self, config: MatrixRewardConfig, mode: ModeConfig, braking_threshold: float = -4.5):
        self.config = config
        self.mode = mode
        self.braking_threshold = braking_threshold
        weights = mode.decision_weights
        self.decision_matrix = np.diag([getattr(weights, row) for row in ROWS])   # A_k1
        self.scales = np.array([getattr(config.scales, row) for row in ROWS])[:, None]

    # --- capped exponentials ---------------------------------------------------------------

    def _exp(self, x: float) -> float:
        cap = self.config.exponent_cap
        return math.exp(x if cap is None else min(x, cap))

    # --- sub-rewards (raw, per step) --------------------------------------------------------

    @staticmethod
    def result(step: StepResult) -> tuple[float, float]:
        """300 per CAV or HV2 leaving by Exit_1 (eq. 21); -60000 if any collision (eq. 22)."""
        exits = sum(1 for a in step.arrivals
                    if a.exit_edge == EXIT_TASK and a.vehicle_class in ('CAV', 'HV2'))
        return 300.0 * exits, -60000.0 if step.collisions else 0.0

    def v_min(self, vehicle: VehicleState) -> float:
        return self.config.v_min.highway if vehicle.on_highway else self.config.v_min.ramp

    def efficiency(self, cavs: Sequence[VehicleState]) -> tuple[float, float]:
        """Summed over CAVs: exp(6 (v - v_min) / v_max) in the band, penalties outside (eq. 23-24)."""
        incentive = punishment = 0.0
        for vehicle in cavs:
            v, v_max, v_min = vehicle.speed, vehicle.lane_speed_limit, self.v_min(vehicle)
            if v > v_max:
                punishment -= self._exp(v - v_max)
            elif v < v_min:
                punishment -= self._exp(1.0 + (v_min - v) / 3.0)
            else:
                incentive += self._exp(6.0 * (v - v_min) / v_max)
        return incentive, punishment

    def comfort(self, vehicles: Sequence[VehicleState], lane_changes: int) -> tuple[float, float]:
        """e^3 per vehicle with |a| <= 2; -2000 per emergency braking - exp(m / 2) (eq. 25-26)."""
        if self.config.comfort_vehicles == 'cav':
            vehicles = [v for v in vehicles if v.is_cav]
        smooth = sum(1 for v in vehicles if -2.0 <= v.acceleration <= 2.0)
        braking = sum(1 for v in vehicles if v.acceleration <= self.braking_threshold)
        cap = self.config.lane_change_cap
        m = lane_changes if cap is None else min(lane_changes, cap)
        return math.exp(3.0) * smooth, -2000.0 * braking - self._exp(m / 2.0)

    def safety_one(self, t_follower: float, t_leader: float) -> tuple[float, float]:
        """The driving hazard diagram (Table 4) on the two time gaps [s] (inf = not closing)."""
        if math.isinf(t_follower) and math.isinf(t_leader):
            return E2, 0.0                                                    # Omega_I3
        t_min, t_max = sorted(min(t, SAFETY_TIME_CAP) for t in (t_follower, t_leader))
        if t_min >= SAFETY_THRESHOLD:
            return min(self._exp((t_min - 5.0) / 2.5), E2), 0.0               # Omega_I1
        if t_max >= SAFETY_THRESHOLD:
            return min(self._exp((t_max - 5.0) / 2.5), E2), -self._exp(4.0 - t_min)  # I2 + P1
        return 0.0, -self._exp(4.0 - t_min) - self._exp(4.0 - t_max)          # P1 + P2

    @staticmethod
    def time_gaps(vehicle: VehicleState, snapshot: TrafficSnapshot) -> tuple[float, float]:
        """t1 (follower, eq. 27) and t2 (leader, eq. 28); inf when the gap is not closing."""
        around = snapshot.neighbours_of(vehicle)
        t1 = t2 = math.inf
        if around.follower is not None and around.follower.speed > vehicle.speed:
            t1 = (vehicle.position - around.follower.position) / (around.follower.speed - vehicle.speed)
        if around.leader is not None and vehicle.speed > around.leader.speed:
            t2 = (around.leader.position - vehicle.position) / (vehicle.speed - around.leader.speed)
        return t1, t2

    def safety(self, cavs: Sequence[VehicleState], snapshot: TrafficSnapshot) -> tuple[float, float]:
        incentive = punishment = 0.0
        for vehicle in cavs:
            i, p = self.safety_one(*self.time_gaps(vehicle, snapshot))
            incentive += i
            punishment += p
        return incentive, punishment

    # --- the matrix --------------------------------------------------------------------------

    def incentive_weights(self, result_p: float, comfort_p: float) -> np.ndarray:
        """A_k2 with the dynamic incentive weights of eq. 20 (s = r_result_P + r_comfort_P)."""
        k_i, k_p = self.mode.incentive, self.mode.punishment
        if self.config.dynamic_weights:
            s = result_p + comfort_p
            incentive = [k_i * math.exp(s / 100000.0), k_i * math.exp(s / 80000.0), k_i,
                         k_i * math.exp(s / 150000.0)]
        else:
            incentive = [k_i] * 4
        return np.column_stack([incentive, [k_p] * 4])

    def combine(self, sub_rewards: np.ndarray) -> RewardBreakdown:
        """tr(A_k1 A_k2 A_r^T) for raw sub-rewards (4 x 2, rows in ROWS order)."""
        weights = self.incentive_weights(sub_rewards[0, 1], sub_rewards[2, 1])
        total = float(np.trace(self.decision_matrix @ weights @ (sub_rewards / self.scales).T))
        return RewardBreakdown(total, sub_rewards, weights)

    def __call__(self, inputs: StepRewardInputs) -> RewardBreakdown:
        vehicles = inputs.step.vehicles
        cavs = [v for v in vehicles if v.is_cav]
        sub_rewards = np.array([
            self.result(inputs.step),
            self.efficiency(cavs),
            self.comfort(vehicles, inputs.recent_lane_changes),
            self.safety(cavs, inputs.snapshot),
        ], dtype=float)
        return self.combine(sub_rewards)


class BaselineReward:
    """Dong et al.'s reward (paper 000's baseline): intention + speed - lane change - collision."""

    def __init__(self, config: BaselineRewardConfig):
        self.config = config

    def __call__(self, inputs: StepRewardInputs) -> RewardBreakdown:
        step = inputs.step
        cavs = [v for v in step.vehicles if v.is_cav]
        exits = sum(1 for a in step.arrivals if a.vehicle_class == 'CAV' and a.exit_edge == EXIT_TASK)
        speed = sum(v.speed / v.lane_speed_limit for v in cavs)
        cav_ids = {v.vehicle_id for v in cavs}
        lane_changes = sum(1 for vehicle_id in step.lane_changers if vehicle_id in cav_ids)
        c = self.config
        total = (c.intention * exits + c.speed * speed - c.lane_change * lane_changes
                 - c.collision * len(step.collisions))
        sub_rewards = np.array([[exits, -len(step.collisions)], [speed, 0.0],
                                [0.0, -lane_changes], [0.0, 0.0]], dtype=float)
        return RewardBreakdown(total, sub_rewards, np.ones((4, 2)))


def make_reward(config: MatrixRewardConfig | BaselineRewardConfig, mode: ModeConfig,
                braking_threshold: float = -4.5) -> MatrixReward | BaselineReward:
    if isinstance(config, BaselineRewardConfig):
        return BaselineReward(config)
    return MatrixReward(config, mode, braking_threshold)
