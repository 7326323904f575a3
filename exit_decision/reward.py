"""The reward function matrix of paper 000 (Section 4; ours: docs/design.md, "Reward") and the
baseline reward.

r = tr(A_k1 A_k2 A_r^T): A_k1 = diag(k_result, k_efficiency, k_comfort, k_safety) (the mode's
decision weights), A_k2 = [[k_iI, k_iP]] (incentive / punishment weights, the incentive ones
dynamic, eq. 20), A_r = [[r_iI, r_iP]] (the sub-rewards of the step, each divided by the
variant's scale).

The reward is computed in two parts so that one experience can be scored under any mode:
- ``MatrixReward.vector`` gives the step's *reward vector*: the (4 rows x [incentive,
  punishment]) sub-rewards, divided by the scales, with the dynamic factors of eq. 20
  (exp(s / c_row), s = r_result_P + r_comfort_P: they do not depend on the mode) already
  multiplied into the incentive column. It is split by owner: each CAV's own terms (its
  exit, speed, comfort, gaps) and the terms no single CAV owns (HV2 exits, a collision with
  no CAV in it, the lane-change count m, humans' comfort when counted).
- ``scalar(vector, mode_weights(mode))`` is then the paper's tr(A_k1 A_k2 A_r^T) exactly:
  linear in the vector, so sums over steps, m-step returns and per-CAV shares are scored the
  same way. Nothing else computes a mode's scalar.

Variants: ``literal`` is the paper as written; ``bounded`` caps every exponent and the
lane-change count (ours: the literal terms reach 1e10) and counts per-step incentives per
step (the calibration of earlier releases, kept for the ablation); ``calibrated`` (ours)
counts the efficiency and smooth-driving incentives per metre driven, so a CAV earns them for
the road it covers, not for the time it stays (per step, faster safe driving never paid:
docs/design.md), while its safety incentive stays per step, which still pays time on the road;
``headway`` (ours, the default since issue 28) counts the safety incentive per metre too,
graded by the time headway kept (``MatrixReward.safety``), Table 4's punishments unchanged;
``traffic`` (ours, issue 39) is ``headway`` plus a MOBIL-style term that charges a CAV, on its
own comfort punishment, the hard braking of the vehicle behind it (``MatrixReward.caused_braking``).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from exit_decision.config import (BaselineRewardConfig, IntentionRewardConfig, MatrixRewardConfig, ModeConfig,
                                  RewardVariantConfig, TermsRewardConfig)
from exit_decision.traffic import CAV, HV2, Neighbours, StepResult, TrafficSnapshot, VehicleState

ROWS = ('result', 'efficiency', 'comfort', 'safety')
#: a reward vector's entries as the tables' columns, row by row: result_I, result_P, efficiency_I, ...
VECTOR_COLUMNS = tuple(f'{row}_{side}' for row in ROWS for side in ('I', 'P'))
RESULT, EFFICIENCY, COMFORT, SAFETY = range(4)
INCENTIVE, PUNISHMENT = 0, 1
SAFETY_TIME_CAP = 10.0      # [s] time gaps longer than this count as 10 s
SAFETY_THRESHOLD = 4.0      # [s] below: the hazard regions of the driving hazard diagram
E2 = math.exp(2.0)
#: Denominators c_row of the dynamic incentive weights (eq. 20); None: static (comfort)
DYNAMIC_DENOMINATORS = (100000.0, 80000.0, None, 150000.0)
#: Length of the network input describing a mode: A_k1's diagonal, then k_I0 and k_P0
WEIGHT_INPUT_SIZE = 6


@dataclass(frozen=True, slots=True)
class StepRewardInputs:
    """What one simulation step contributes to the reward."""
    step: StepResult
    snapshot: TrafficSnapshot
    recent_lane_changes: int    # m: lane changes of all vehicles in the last 0.5 s


@dataclass
class RewardVector:
    """Mode-independent reward of a step or a sum of steps, split by owner (module docstring)."""
    per_vehicle: dict[str, np.ndarray] = field(default_factory=dict)   # CAV id -> (4, 2)
    shared: np.ndarray = field(default_factory=lambda: np.zeros((4, 2)))

    def total(self) -> np.ndarray:
        """(4, 2): the whole step's vector (what the paper's global reward is made of)."""
        return self.shared + sum(self.per_vehicle.values(), np.zeros((4, 2)))


# --- modes as weights -----------------------------------------------------------------------

def weight_input(mode: ModeConfig) -> np.ndarray:
    """The six numbers that describe a mode: A_k1's diagonal (in ROWS order), k_I0, k_P0."""
    d = mode.decision_weights
    return np.array([*(getattr(d, row) for row in ROWS), mode.incentive, mode.punishment])


def weights_of_input(weights: np.ndarray) -> np.ndarray:
    """(..., 6) weight inputs -> (..., 4, 2) multipliers of the reward vector."""
    weights = np.asarray(weights, dtype=float)
    return weights[..., :4, None] * weights[..., None, 4:6]


def mode_weights(mode: ModeConfig) -> np.ndarray:
    """(4, 2) multipliers of the reward vector for a mode: A_k1[row] * [k_I0, k_P0]."""
    return weights_of_input(weight_input(mode))


def scalar(vector: np.ndarray, weights: np.ndarray) -> np.ndarray | float:
    """tr(A_k1 A_k2 A_r^T) of reward vectors (..., 4, 2) under weights (..., 4, 2)."""
    return (np.asarray(vector) * weights).sum(axis=(-2, -1))


def credit(own: np.ndarray, shared: np.ndarray, acting: np.ndarray) -> np.ndarray:
    """(N, 4, 2) per-CAV credit of one decision's reward vectors: each acting row's own terms
    (``own``, (N, 4, 2)) plus an equal share of the terms no CAV owns (``shared``, (4, 2));
    zeros on the rows that did not act (``acting``, (N,) bool)."""
    shares = np.where(acting[:, None, None], own, 0.0)
    if acting.any():
        shares[acting] += shared / acting.sum()
    return shares


# --- the matrix -----------------------------------------------------------------------------

class MatrixReward:
    """Reward vectors of the reward function matrix for one variant (any mode scores them)."""

    def __init__(self, config: MatrixRewardConfig, step_length: float, braking_threshold: float = -4.5):
        self.config = config
        self.step_length = step_length
        self.braking_threshold = braking_threshold
        self.scales = np.array([getattr(config.scales, row) for row in ROWS])[:, None]

    def weights(self, mode: ModeConfig) -> np.ndarray:
        return mode_weights(mode)

    def _exp(self, x: float) -> float:
        cap = self.config.exponent_cap
        return math.exp(x if cap is None else min(x, cap))

    def _per(self, vehicle: VehicleState) -> float:
        """What one step of a per-step incentive counts for: 1, or the metres driven in it."""
        return vehicle.speed * self.step_length if self.config.incentive_per == 'metre' else 1.0

    # --- sub-rewards (raw) --------------------------------------------------------------------

    def v_min(self, vehicle: VehicleState) -> float:
        return self.config.v_min.highway if vehicle.on_highway else self.config.v_min.ramp

    def efficiency_one(self, vehicle: VehicleState) -> tuple[float, float]:
        """exp(6 (v - v_min) / v_max) in the band, penalties outside (eq. 23-24)."""
        v, v_max, v_min = vehicle.speed, vehicle.lane_speed_limit, self.v_min(vehicle)
        if v > v_max:
            return 0.0, -self._exp(v - v_max)
        if v < v_min:
            return 0.0, -self._exp(1.0 + (v_min - v) / 3.0)
        return self._exp(6.0 * (v - v_min) / v_max) * self._per(vehicle), 0.0

    def comfort_one(self, vehicle: VehicleState) -> tuple[float, float]:
        """e^3 with |a| <= 2; -2000 for an emergency braking (eq. 25-26, per vehicle)."""
        smooth = math.exp(3.0) * self._per(vehicle) if -2.0 <= vehicle.acceleration <= 2.0 else 0.0
        return smooth, -2000.0 if vehicle.acceleration <= self.braking_threshold else 0.0

    def lane_change_punishment(self, lane_changes: int) -> float:
        """-exp(m / 2) for the lane changes of the last 0.5 s (eq. 26)."""
        cap = self.config.lane_change_cap
        return -self._exp((lane_changes if cap is None else min(lane_changes, cap)) / 2.0)

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

    def headway_grade(self, vehicle: VehicleState, around: Neighbours) -> float:
        """0..1: the smaller of the CAV's time headway to its leader (bumper gap over its own
        speed) and its follower's to it (gap over the follower's speed), over ``headway_full``;
        no vehicle, or one standing, counts as the full headway."""
        full = self.config.headway_full
        headway = full
        if around.leader is not None and vehicle.speed > 0:
            headway = min(headway, around.leader_gap / vehicle.speed)
        if around.follower is not None and around.follower.speed > 0:
            headway = min(headway, around.follower_gap / around.follower.speed)
        return max(headway, 0.0) / full

    def safety(self, vehicle: VehicleState, snapshot: TrafficSnapshot) -> tuple[float, float]:
        """The safe-gaps row of one CAV: Table 4's punishments on the two time gaps; its
        incentive as Table 4 reads (``hazard_diagram``), or (``headway``) e^2 per metre driven
        times the headway grade, so a standing CAV earns nothing and a closer, still-safe gap
        earns less (a choice the mode's weights price)."""
        around = snapshot.neighbours_of(vehicle)
        incentive, punishment = self.safety_one(*self.time_gaps(vehicle, snapshot, around))
        if self.config.safety_incentive == 'headway':
            incentive = E2 * self.headway_grade(vehicle, around) * vehicle.speed * self.step_length
        return incentive, punishment

    @staticmethod
    def time_gaps(vehicle: VehicleState, snapshot: TrafficSnapshot,
                  around: Neighbours | None = None) -> tuple[float, float]:
        """t1 (follower, eq. 27) and t2 (leader, eq. 28); inf when the gap is not closing."""
        around = snapshot.neighbours_of(vehicle) if around is None else around
        t1 = t2 = math.inf
        if around.follower is not None and around.follower.speed > vehicle.speed:
            t1 = (vehicle.position - around.follower.position) / (around.follower.speed - vehicle.speed)
        if around.leader is not None and vehicle.speed > around.leader.speed:
            t2 = (around.leader.position - vehicle.position) / (vehicle.speed - around.leader.speed)
        return t1, t2

    def caused_braking(self, step: StepResult, snapshot: TrafficSnapshot) -> dict[str, float]:
        """The ``traffic`` variant's MOBIL-style term, raw, per CAV charged: every vehicle
        decelerating harder than ``b_safe`` whose leader (own corridor, bumper gap within
        ``leader_range``) is a CAV costs that CAV -weight x (deceleration - b_safe) this step
        (linear in the excess, as MOBIL's accelerations are: weight 1000 makes a follower at
        6 m/s^2 cost what the CAV's own emergency braking step costs, -2000). Whoever caused it, a
        lane change in front of the follower or a braking ahead of it, the leader of the step is
        charged; a human leader charges nobody, nor does a released CAV (out of the task).
        Empty when the variant has no such term."""
        term = self.config.caused_braking
        charges: dict[str, float] = {}
        if term is None:
            return charges
        for vehicle in step.vehicles:
            excess = -vehicle.acceleration - term.b_safe
            if excess <= 0:
                continue
            around = snapshot.neighbours_of(vehicle)
            leader = around.leader
            if (leader is not None and leader.is_cav and around.leader_gap <= term.leader_range
                    and leader.vehicle_id not in step.released):
                charges[leader.vehicle_id] = charges.get(leader.vehicle_id, 0.0) - term.weight * excess
        return charges

    # --- the step's vector --------------------------------------------------------------------

    def raw(self, inputs: StepRewardInputs) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Unscaled sub-rewards (4, 2) per CAV and shared, before the dynamic factors: 300 per
        CAV or HV2 leaving by the task exit, -60000 once if any collision (eq. 21-22; owned by
        the CAVs in it, shared if none), then eq. 23-28 per vehicle, and (``traffic``) the hard
        braking each CAV causes behind it on its comfort punishment (so it enters eq. 20's s
        like the CAV's own emergency braking). A CAV released after a missed exit earns and
        loses nothing more but its collisions."""
        step, snapshot = inputs.step, inputs.snapshot
        shared = np.zeros((4, 2))
        own: dict[str, np.ndarray] = {}

        def of(vehicle_id: str) -> np.ndarray:
            return own.setdefault(vehicle_id, np.zeros((4, 2)))

        for arrival in step.arrivals:
            if arrival.reached_target and arrival.vehicle_class == CAV:
                of(arrival.vehicle_id)[RESULT, INCENTIVE] += 300.0
            elif arrival.reached_target and arrival.vehicle_class == HV2:
                shared[RESULT, INCENTIVE] += 300.0
        if step.collisions:
            colliders = sorted({vid for c in step.collisions for vid, cls in
                                ((c.collider, c.collider_class), (c.victim, c.victim_class)) if cls == CAV})
            for vehicle_id in colliders:
                of(vehicle_id)[RESULT, PUNISHMENT] -= 60000.0 / len(colliders)
            if not colliders:
                shared[RESULT, PUNISHMENT] -= 60000.0
        for vehicle in step.vehicles:
            if vehicle.vehicle_id in step.released:
                continue   # out of the task: its metres after a missed exit earn nothing
            if vehicle.is_cav:
                cell = of(vehicle.vehicle_id)
                cell[EFFICIENCY] += self.efficiency_one(vehicle)
                cell[COMFORT] += self.comfort_one(vehicle)
                cell[SAFETY] += self.safety(vehicle, snapshot)
            elif self.config.comfort_vehicles == 'all':
                shared[COMFORT] += self.comfort_one(vehicle)
        for vehicle_id, charge in self.caused_braking(step, snapshot).items():
            of(vehicle_id)[COMFORT, PUNISHMENT] += charge
        shared[COMFORT, PUNISHMENT] += self.lane_change_punishment(inputs.recent_lane_changes)
        return own, shared

    def dynamic_factors(self, result_p: float, comfort_p: float) -> np.ndarray:
        """(4,) the factors of eq. 20 on the incentive weights, s = r_result_P + r_comfort_P."""
        if not self.config.dynamic_weights:
            return np.ones(4)
        s = result_p + comfort_p
        return np.array([1.0 if c is None else math.exp(s / c) for c in DYNAMIC_DENOMINATORS])

    def vector(self, inputs: StepRewardInputs) -> RewardVector:
        own, shared = self.raw(inputs)
        punishments = shared[:, PUNISHMENT] + sum((v[:, PUNISHMENT] for v in own.values()), np.zeros(4))
        factor = np.ones((4, 2))
        factor[:, INCENTIVE] = self.dynamic_factors(punishments[RESULT], punishments[COMFORT])
        factor /= self.scales
        return RewardVector({vid: v * factor for vid, v in own.items()}, shared * factor)


class ModelessReward:
    """A reward without modes: its vector holds its terms already weighted, so every mode
    scores it the same (weights of ones)."""

    def __init__(self, config):
        self.config = config

    def weights(self, mode: ModeConfig) -> np.ndarray:
        return np.ones((4, 2))


class BaselineReward(ModelessReward):
    """Dong et al.'s reward (paper 000's baseline): intention + speed - lane change - collision,
    one entry each of the vector."""

    def vector(self, inputs: StepRewardInputs) -> RewardVector:
        step, c = inputs.step, self.config
        result = RewardVector()
        for vehicle in step.vehicles:
            if vehicle.is_cav:
                result.per_vehicle[vehicle.vehicle_id] = np.zeros((4, 2))
                result.per_vehicle[vehicle.vehicle_id][EFFICIENCY, INCENTIVE] = \
                    c.speed * vehicle.speed / vehicle.lane_speed_limit
        for arrival in step.arrivals:
            if arrival.vehicle_class == CAV and arrival.reached_target:
                result.per_vehicle.setdefault(arrival.vehicle_id, np.zeros((4, 2)))[RESULT, INCENTIVE] += c.intention
        for vehicle_id in step.lane_changers:
            if vehicle_id in result.per_vehicle:
                result.per_vehicle[vehicle_id][COMFORT, PUNISHMENT] -= c.lane_change
        result.shared[RESULT, PUNISHMENT] = -c.collision * len(step.collisions)
        return result


def own_collisions(step: StepResult) -> tuple[dict[str, int], int]:
    """Collisions per CAV in them, and the number with no CAV in them."""
    per_cav: dict[str, int] = {}
    for collision in step.collisions:
        for vehicle_id, cls in ((collision.collider, collision.collider_class), (collision.victim, collision.victim_class)):
            if cls == CAV:
                per_cav[vehicle_id] = per_cav.get(vehicle_id, 0) + 1
    return per_cav, sum(not c.involves_cav for c in step.collisions)


class TermsReward(ModelessReward):
    """Papers 002 and 003: a weighted sum of each CAV's terms (the weights in the config; paper
    002: safety / efficiency / lane change 0.5 / 0.4 / 0.1). Terms: a collision the CAV is in,
    its normalised speed (v - v_min) / (lane limit - v_min) in [0, 1] and a constant per step on
    the road, its lane changes, and once a clean exit (a CAV leaves the road only if it never
    collided: colliders are removed). Released CAVs earn nothing more."""

    config: TermsRewardConfig

    def vector(self, inputs: StepRewardInputs) -> RewardVector:
        step, c = inputs.step, self.config
        result = RewardVector()

        def of(vehicle_id: str) -> np.ndarray:
            return result.per_vehicle.setdefault(vehicle_id, np.zeros((4, 2)))

        for vehicle in step.vehicles:
            if vehicle.is_cav and vehicle.vehicle_id not in step.released:
                v_min = c.v_min.highway if vehicle.on_highway else c.v_min.ramp
                band = max(vehicle.lane_speed_limit - v_min, 1e-6)
                of(vehicle.vehicle_id)[EFFICIENCY, INCENTIVE] += c.step_weight * (
                    c.speed * float(np.clip((vehicle.speed - v_min) / band, 0.0, 1.0)) + c.step)
        for vehicle_id in step.lane_changers:
            if vehicle_id in result.per_vehicle:
                of(vehicle_id)[COMFORT, PUNISHMENT] += c.lane_change
        for arrival in step.arrivals:
            if arrival.vehicle_class == CAV:
                of(arrival.vehicle_id)[RESULT, INCENTIVE] += c.clean_exit
        per_cav, without_cav = own_collisions(step)
        for vehicle_id, count in per_cav.items():
            of(vehicle_id)[SAFETY, PUNISHMENT] += c.collision * count
        result.shared[SAFETY, PUNISHMENT] = c.collision * without_cav
        return result


class IntentionReward(ModelessReward):
    """Paper 001's reward (eq. 2-5), per CAV: the intention reward R_I, the crash reward
    R_C = -(vehicles in its collisions) / 2 and the speed reward R_S = v / v_max - offset,
    aggregated as w_I R_I R_S + w_C R_C where R_I > 0, else w_I R_I + w_C R_C (eq. 5).

    R_I by where the CAV is (the paper's Fig. 6 gradient, on our road): ``on_route`` per step
    in a lane from which the target exit is reached as planned (``RoadGeometry.route_lanes``)
    or on the target ramp, ``off_route`` per step elsewhere, ``reached`` / ``missed`` once on
    leaving by the target exit / another one. Per-step terms count per simulation step times
    ``step_weight``. Released CAVs earn nothing more."""

    def __init__(self, config: IntentionRewardConfig, route_lanes: Callable[[float], range]):
        super().__init__(config)
        self.route_lanes = route_lanes

    def intention(self, vehicle: VehicleState) -> float:
        on_route = vehicle.lane_index in self.route_lanes(vehicle.position) if vehicle.on_highway else True
        return self.config.on_route if on_route else self.config.off_route

    def vector(self, inputs: StepRewardInputs) -> RewardVector:
        step, c = inputs.step, self.config
        result = RewardVector()
        per_cav, without_cav = own_collisions(step)
        crash = {vehicle_id: -count for vehicle_id, count in per_cav.items()}   # 2 vehicles each, / 2
        intention: dict[str, tuple[float, float]] = {}   # vehicle id -> (R_I, R_S), per step
        for vehicle in step.vehicles:
            if vehicle.is_cav and vehicle.vehicle_id not in step.released:
                intention[vehicle.vehicle_id] = (c.step_weight * self.intention(vehicle),
                                                 vehicle.speed / c.speed_max - c.speed_offset)
        for arrival in step.arrivals:
            if arrival.vehicle_class == CAV:
                intention[arrival.vehicle_id] = (c.reached if arrival.reached_target else c.missed, 1.0)
        for vehicle_id in intention.keys() | crash.keys():
            r_i, r_s = intention.get(vehicle_id, (0.0, 0.0))
            cell = result.per_vehicle.setdefault(vehicle_id, np.zeros((4, 2)))
            if r_i > 0:
                cell[RESULT, INCENTIVE] = c.intention_weight * r_i * r_s
            else:
                cell[RESULT, PUNISHMENT] = c.intention_weight * r_i
            cell[SAFETY, PUNISHMENT] = c.collision_weight * crash.get(vehicle_id, 0)
        result.shared[SAFETY, PUNISHMENT] = -c.collision_weight * without_cav
        return result


RewardFunction = MatrixReward | BaselineReward | TermsReward | IntentionReward


def make_reward(config: RewardVariantConfig, step_length: float, braking_threshold: float = -4.5,
                route_lanes: Callable[[float], range] | None = None) -> RewardFunction:
    """The reward of a variant; paper 001's needs ``route_lanes`` (the road geometry's)."""
    if isinstance(config, BaselineRewardConfig):
        return BaselineReward(config)
    if isinstance(config, TermsRewardConfig):
        return TermsReward(config)
    if isinstance(config, IntentionRewardConfig):
        if route_lanes is None:
            raise ValueError('the intention reward needs the road geometry\'s route lanes')
        return IntentionReward(config, route_lanes)
    return MatrixReward(config, step_length, braking_threshold)
