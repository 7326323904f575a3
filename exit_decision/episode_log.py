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
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from exit_decision.reward import scalar
from exit_decision.traffic import CAV, HV2, StepResult, TrafficSnapshot

METRICS = ('v_AVs', 'v_s', 'p_collision', 'p_collision_CAV', 'N_braking', 'N_braking_CAV', 'braking_steps',
           'headway_CAV', 'p_CAV', 'p_HV2', 'reward', 'steps')
HEADWAY_RANGE = 100.0      # [m] a leader farther than this does not set the CAV's headway
HEADWAY_MIN_SPEED = 5.0    # [m/s] below, a headway says nothing about the style (queues, stops)


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
    entered: dict[str, set[str]] = field(default_factory=dict)
    target_exits: dict[str, int] = field(default_factory=dict)   # class -> vehicles that left by the target exit
    reward_weights: np.ndarray | None = None    # (4, 2) multipliers of the mode the return is scored under
    reward_vector: np.ndarray = field(default_factory=lambda: np.zeros((4, 2)))  # summed over steps
    peak_vehicles: int = 0   # most vehicles on the road at one step: what the graph's N must hold

    def record(self, step: StepResult, reward_vector: np.ndarray | None = None,
               snapshot: TrafficSnapshot | None = None) -> None:
        """One step; the CAVs' headways need the step's ``snapshot`` (not counted without it)."""
        self.steps += 1
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
            'headway_CAV': self.headway_sum / self.headway_steps if self.headway_steps else nan,
            'p_CAV': self.target_exits.get(CAV, 0) / n_cav if n_cav else nan,
            'p_HV2': self.target_exits.get(HV2, 0) / n_hv2 if n_hv2 else nan,
            'reward': float(scalar(self.reward_vector, self.reward_weights)) if self.reward_weights is not None else nan,
            'steps': float(self.steps),
        }
