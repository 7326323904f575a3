"""Evaluation runs: a controller (or SUMO's own drivers) on fixed seeds, metrics per episode."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from tqdm import tqdm

from exit_decision.agents.shield import Decision
from exit_decision.env import ExitDecisionEnv
from exit_decision.graph import TrafficGraph
from exit_decision.traffic import VehicleState


class Controller(Protocol):
    name: str

    def decide(self, graph: TrafficGraph, vehicles: Sequence[VehicleState]) -> Decision: ...


@dataclass
class EvaluationResult:
    episodes: list[dict[str, float]] = field(default_factory=list)
    action_counts: np.ndarray | None = None   # how often each action of the grid was chosen
    overrides: int = 0                         # first choices the shield refused
    decisions: int = 0                         # CAV decisions made


def run_episode(env: ExitDecisionEnv, controller: Controller | None, seed: int,
                result: EvaluationResult) -> dict[str, float]:
    """One episode; ``controller`` None means the env's CAVs are driven by SUMO."""
    env.reset(seed=seed)
    keep = env.actions.index(0, 0.0)
    if result.action_counts is None:
        result.action_counts = np.zeros(env.actions.size, dtype=np.int64)
    done = False
    while not done:
        action = np.full(env.graph.num_nodes, keep)
        if controller is not None:
            decision = controller.decide(env.graph, env.sim.snapshot.vehicles)
            row_of = {vid: row for row, vid in enumerate(env.graph.vehicle_ids) if vid}
            for vehicle_id, index in decision.actions.items():
                action[row_of[vehicle_id]] = index
                result.action_counts[index] += 1
            result.overrides += decision.overridden
            result.decisions += len(decision.actions)
        _, _, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
    return env.episode_log.metrics()


def evaluate(env: ExitDecisionEnv, controller: Controller | None, seeds: Sequence[int],
             progress: bool = True) -> EvaluationResult:
    result = EvaluationResult()
    for seed in tqdm(seeds, desc=f'evaluate {controller.name if controller else "sumo"}', unit='ep',
                     disable=not progress):
        metrics = run_episode(env, controller, seed, result)
        result.episodes.append({'seed': seed, **metrics})
    return result
