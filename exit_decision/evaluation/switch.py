"""What a mode switch changes: the driving of the CAVs on the road at the switch, before and after.

For the CAVs on the road at the switch time t, over [t - window, t) and [t, t + window): their
mean speed, their mean time headway (as ``episode_log``'s: bumper gap to the leader in the own
corridor over own speed, leader within ``HEADWAY_RANGE``, speed above ``HEADWAY_MIN_SPEED``) and
their hard-braking events (a contiguous run of steps at or below the threshold counts once, in
the window where it begins). The same figures of the same seed without the switch tell what the
switch did and what the traffic did anyway (issue 28, the main job shows the switch).
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from exit_decision.env import ExitDecisionEnv
from exit_decision.episode_log import HEADWAY_MIN_SPEED, HEADWAY_RANGE
from exit_decision.driving.episode import play_episode
from exit_decision.driving.interface import Driver, StepDecision
from exit_decision.model.modes import Mode
from exit_decision.traffic import TrafficSnapshot, VehicleState

#: the episode's (time [s], vehicles) of every simulation step, in order
Steps = list[tuple[float, list[VehicleState]]]


@dataclass(frozen=True)
class WindowFigures:
    speed: float           # [m/s] mean over the CAV-steps of the window
    headway: float         # [s] mean over the CAV-steps with a leader in range (nan: none)
    hard_brakings: int     # events that began in the window
    cavs: int              # the CAVs followed (on the road at the switch)


def switch_windows(steps: Iterable[tuple[float, list[VehicleState]]], switch_time: float, window: float = 10.0,
                   braking_threshold: float = -4.5) -> tuple[WindowFigures, WindowFigures]:
    """(before, after) the switch for the CAVs on the road at ``switch_time``; ``steps``: the
    episode's (time [s], vehicles) in order."""
    steps = [(time, vehicles) for time, vehicles in steps if switch_time - window <= time < switch_time + window]
    at_switch = min(steps, key=lambda step: abs(step[0] - switch_time))[1] if steps else []
    followed = {v.vehicle_id for v in at_switch if v.is_cav}
    sums = {side: {'speed': [], 'headway': [], 'brakings': 0} for side in ('before', 'after')}
    braking: set[str] = set()
    for time, vehicles in steps:
        side = sums['before' if time < switch_time else 'after']
        snapshot = None
        for vehicle in vehicles:
            if vehicle.vehicle_id not in followed:
                continue
            side['speed'].append(vehicle.speed)
            if vehicle.speed > HEADWAY_MIN_SPEED:
                snapshot = snapshot or TrafficSnapshot(vehicles)
                gap = snapshot.neighbours_of(vehicle).leader_gap
                if gap <= HEADWAY_RANGE:
                    side['headway'].append(gap / vehicle.speed)
            if vehicle.acceleration <= braking_threshold:
                if vehicle.vehicle_id not in braking:
                    side['brakings'] += 1
                    braking.add(vehicle.vehicle_id)
            else:
                braking.discard(vehicle.vehicle_id)

    def figures(side: dict) -> WindowFigures:
        mean = lambda values: float(np.mean(values)) if values else float('nan')  # noqa: E731
        return WindowFigures(mean(side['speed']), mean(side['headway']), side['brakings'], len(followed))

    return figures(sums['before']), figures(sums['after'])


@dataclass
class PolicyEpisode:
    """One episode in the environment: every step's (time, vehicles), and its reward vectors
    summed before the switch and from it on (the whole episode's in ``before`` without one)."""
    steps: Steps
    before: np.ndarray      # (4, 2)
    after: np.ndarray       # (4, 2)


def policy_steps(env: ExitDecisionEnv, driver: Driver, seed: int, until: float = float('inf'),
                 switch: tuple[float, Mode] | None = None) -> PolicyEpisode:
    """One episode in the environment (no ROS) up to ``until`` [s] (default: its end), the
    driver in the mode it was given, or from ``switch`` = (time, mode) on in that one (every
    option held ends there, as in the decision node)."""
    run = PolicyEpisode([], np.zeros((4, 2)), np.zeros((4, 2)))
    switched = False

    def on_start() -> None:
        run.steps.append((env.sim.state.time, list(env.sim.snapshot.vehicles)))

    def on_step(decision: StepDecision, info: dict, terminated: bool, truncated: bool) -> bool:
        nonlocal switched
        per_row, shared = info['reward_vector']
        if switched:
            run.after += per_row.sum(0) + shared
        else:
            run.before += per_row.sum(0) + shared
        run.steps.extend((result.time, result.vehicles) for result in info['step_results'])
        if switch is not None and not switched and env.sim.state.time >= switch[0] - 1e-9:
            driver.set_mode(switch[1])
            switched = True
        return run.steps[-1][0] >= until

    play_episode(env, driver, seed, on_step, on_start)
    return run

