"""One episode's log and its metrics (paper 000, Section 5.2; defined below).

``EpisodeLog.record`` takes each step's result and its reward vector (the return is the
vectors' sum scored under ``reward_weights``, the env's mode, by linearity); ``EpisodeLog.metrics`` gives: v_AVs and v_s (mean speed over CAV-steps / all
vehicle-steps), p_collision (collisions / CAVs, the paper's definition) and p_collision_CAV
(collisions involving a CAV / CAVs), N_braking (emergency-braking events: a contiguous run
of steps at or below the threshold counts once) and braking vehicle-steps, N_braking_CAV (the
CAVs' own events), headway_CAV (mean time headway of CAVs: bumper gap to the leader in the own
corridor over own speed, over the CAV-steps with a leader within ``HEADWAY_RANGE`` and a speed
above ``HEADWAY_MIN_SPEED``; what the modes' driving styles differ in), p_CAV and p_HV2
(left by the target exit / entered), the episode reward and the steps. Kept below the environment,
which records into it; evaluation summarises the metrics.

What the traffic pays for the CAVs (issue 39; these need the step's snapshot, NaN without it):
N_braking_caused_CAV, the emergency-braking events of N_braking (any vehicle, CAVs included)
whose leader at the event's first step is a CAV within ``CAUSED_RANGE`` (bumper gap, own
corridor): the CAV-caused share of N_braking. min_TTC, the episode's smallest time to
collision of any vehicle to its leader in its own corridor (bumper gap over the closing speed,
a gap that is not closing has none), and min_TTC_CAV, the same over followers whose leader is
a CAV. Both are capped at ``TTC_CAP`` (an episode without a closing gap scores the cap): the
summaries drop values that are not finite, so inf or NaN would leave the safest episodes out
of a mean and bias it low.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from exit_decision.reward import scalar
from exit_decision.traffic import CAV, HV2, StepResult, TrafficSnapshot

METRICS = ('v_AVs', 'v_s', 'p_collision', 'p_collision_CAV', 'N_braking', 'N_braking_CAV', 'braking_steps',
           'N_braking_caused_CAV', 'min_TTC', 'min_TTC_CAV', 'headway_CAV', 'p_CAV', 'p_HV2', 'reward', 'steps')
HEADWAY_RANGE = 100.0      # [m] a leader farther than this does not set the CAV's headway
HEADWAY_MIN_SPEED = 5.0    # [m/s] below, a headway says nothing about the style (queues, stops)
CAUSED_RANGE = 50.0        # [m] a CAV leader this close is held responsible (the `traffic` reward's leader_range)
TTC_CAP = 10.0             # [s] the largest min_TTC reported (the reward's time-gap cap, SAFETY_TIME_CAP)


@dataclass
class EpisodeLog:
    braking_threshold: float = -4.5
    steps: int = 0
    cav_speed_sum: float = 0.0
    cav_steps: int = 0
    speed_sum: float = 0.0
    vehicle_steps: int = 0
    collisions: int = 0
    cav_collisions: int = 0
    braking_events: int = 0
    braking_steps: int = 0
    cav_braking_events: int = 0
    headway_sum: float = 0.0
    headway_steps: int = 0
    caused_braking_events: int = 0
    min_ttc: float = TTC_CAP
    min_ttc_cav: float = TTC_CAP
    traffic_steps: int = 0    # steps recorded with a snapshot: the traffic metrics are NaN without one
    entered: dict[str, set[str]] = field(default_factory=dict)
    target_exits: dict[str, int] = field(default_factory=dict)   # class -> vehicles that left by the target exit
    reward_weights: np.ndarray | None = None    # (4, 2) multipliers of the mode the return is scored under
    reward_vector: np.ndarray = field(default_factory=lambda: np.zeros((4, 2)))  # summed over steps
    peak_vehicles: int = 0   # most vehicles on the road at one step: what the graph's N must hold

    def record(self, step: StepResult, reward_vector: np.ndarray | None = None,
               snapshot: TrafficSnapshot | None = None) -> None:
        """One step; the CAVs' headways and what the traffic pays need the step's ``snapshot``
        (not counted without it)."""
        self.steps += 1
        if snapshot is not None:
            self._record_traffic(step, snapshot)
        self.peak_vehicles = max(self.peak_vehicles, len(step.vehicles))
        for vehicle in step.vehicles:
            self.entered.setdefault(vehicle.vehicle_class, set()).add(vehicle.vehicle_id)
            self.speed_sum += vehicle.speed
            self.vehicle_steps += 1
            if vehicle.is_cav:
                self.cav_speed_sum += vehicle.speed
                self.cav_steps += 1
                if snapshot is not None and vehicle.speed > HEADWAY_MIN_SPEED:
                    gap = snapshot.neighbours_of(vehicle).leader_gap
                    if gap <= HEADWAY_RANGE:
                        self.headway_sum += gap / vehicle.speed
                        self.headway_steps += 1
            self.braking_steps += vehicle.acceleration <= self.braking_threshold
        self.braking_events += len(step.braking_starts)
        if step.braking_starts:
            cavs = {v.vehicle_id for v in step.vehicles if v.is_cav}
            self.cav_braking_events += sum(vehicle_id in cavs for vehicle_id in step.braking_starts)
        self.collisions += len(step.collisions)
        self.cav_collisions += sum(1 for c in step.collisions if c.involves_cav)
        for arrival in step.arrivals:
            if arrival.reached_target:
                self.target_exits[arrival.vehicle_class] = self.target_exits.get(arrival.vehicle_class, 0) + 1
        if reward_vector is not None:
            self.reward_vector += reward_vector

    def _record_traffic(self, step: StepResult, snapshot: TrafficSnapshot) -> None:
        """Every vehicle's time to collision with its leader, and the braking events whose
        leader is a CAV (module docstring)."""
        self.traffic_steps += 1
        starts = set(step.braking_starts)
        for vehicle, leader, gap in snapshot.leader_pairs():
            if vehicle.vehicle_id in starts and leader.is_cav and gap <= CAUSED_RANGE:
                self.caused_braking_events += 1
            closing = vehicle.speed - leader.speed
            if closing > 0:
                ttc = max(gap, 0.0) / closing
                self.min_ttc = min(self.min_ttc, ttc)
                if leader.is_cav:
                    self.min_ttc_cav = min(self.min_ttc_cav, ttc)

    def count(self, vehicle_class: str) -> int:
        return len(self.entered.get(vehicle_class, ()))

    def metrics(self) -> dict[str, float]:
        n_cav, n_hv2 = self.count(CAV), self.count(HV2)
        nan = float('nan')
        return {
            'v_AVs': self.cav_speed_sum / self.cav_steps if self.cav_steps else nan,
            'v_s': self.speed_sum / self.vehicle_steps if self.vehicle_steps else nan,
            'p_collision': self.collisions / n_cav if n_cav else nan,
            'p_collision_CAV': self.cav_collisions / n_cav if n_cav else nan,
            'N_braking': float(self.braking_events),
            'N_braking_CAV': float(self.cav_braking_events),
            'braking_steps': float(self.braking_steps),
            'N_braking_caused_CAV': float(self.caused_braking_events) if self.traffic_steps else nan,
            'min_TTC': self.min_ttc if self.traffic_steps else nan,
            'min_TTC_CAV': self.min_ttc_cav if self.traffic_steps else nan,
            'headway_CAV': self.headway_sum / self.headway_steps if self.headway_steps else nan,
            'p_CAV': self.target_exits.get(CAV, 0) / n_cav if n_cav else nan,
            'p_HV2': self.target_exits.get(HV2, 0) / n_hv2 if n_hv2 else nan,
            'reward': float(scalar(self.reward_vector, self.reward_weights)) if self.reward_weights is not None else nan,
            'steps': float(self.steps),
        }
