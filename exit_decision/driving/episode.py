"""The one episode loop: a driver plays one episode in the environment.

Evaluation, the sweeps, the switch table, ``exit-decision run`` and training all play their
episodes here; what each needs besides the metrics it takes in ``on_step`` (training collects
its transitions there, the switch table the vehicles of every step, ``--show`` draws them).
"""
from __future__ import annotations

from collections.abc import Callable

from exit_decision.driving.interface import Driver, StepDecision
from exit_decision.env import ExitDecisionEnv

#: after each decision step: (the decision, the step's info, terminated, truncated); True stops
#: the episode there (its metrics so far are returned)
OnStep = Callable[[StepDecision, dict, bool, bool], bool | None]


def play_episode(env: ExitDecisionEnv, driver: Driver, seed: int, on_step: OnStep | None = None,
                 on_start: Callable[[], None] | None = None) -> dict[str, float]:
    """One episode of ``seed`` driven by ``driver`` (reset first: no option held from an earlier
    episode); ``on_start`` runs once the environment is reset. Returns the episode log's metrics."""
    env.reset(seed=seed)
    driver.reset()
    if on_start is not None:
        on_start()
    while True:
        decision = driver.decide(env.graph, env.sim.snapshot, env.sim.state.time)
        _, _, terminated, truncated, info = env.step_commands(decision.commands)
        stop = on_step is not None and on_step(decision, info, terminated, truncated)
        if terminated or truncated or stop:
            return env.episode_log.metrics()
