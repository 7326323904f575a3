"""Evaluation runs: a controller (or SUMO's own drivers) on fixed seeds, metrics per episode."""
from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from tqdm import tqdm

from exit_decision.agents.options import OptionExecutor
from exit_decision.agents.shield import Decision
from exit_decision.env import ExitDecisionEnv
from exit_decision.errors import PolicyError
from exit_decision.graph import TrafficGraph
from exit_decision.model.modes import ModeWeights
from exit_decision.model.driving import PolicyDriver
from exit_decision.model.policy import PolicyController, load_controller
from exit_decision.reward import scalar
from exit_decision.shield_overrides import shield_overrides
from exit_decision.traffic import TrafficSnapshot, VehicleState
from exit_decision.visualization.episodes import EpisodeRecorder, ShowEpisodes


class Controller(Protocol):
    name: str

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot) -> Decision: ...


@dataclass
class EvaluationResult:
    action_counts: np.ndarray | None = None   # how often each action of the grid was chosen
    overrides: int = 0                         # first choices the shield refused
    decisions: int = 0                         # CAV decisions made


def run_episode(env: ExitDecisionEnv, controller: Controller | None, seed: int,
                result: EvaluationResult, recorder: EpisodeRecorder | None = None) -> dict[str, float]:
    """One episode; ``controller`` None means the env's CAVs are driven by SUMO; ``recorder``
    (evaluate --show) takes every step and decision and draws the episode at its end."""
    env.reset(seed=seed)
    if recorder is not None:
        recorder.start(env)
    keep = env.actions.index(0, 0.0)
    if result.action_counts is None:
        result.action_counts = np.zeros(env.actions.size, dtype=np.int64)
    done = False
    while not done:
        action = np.full(env.graph.num_nodes, keep)
        if controller is not None:
            decision = controller.decide(env.graph, env.sim.snapshot)
            row_of = env.graph.row_of()
            for vehicle_id, index in decision.actions.items():
                action[row_of[vehicle_id]] = index
                result.action_counts[index] += 1
            result.overrides += decision.overridden
            result.decisions += len(decision.actions)
            if recorder is not None:
                recorder.decide(env.commands(action),
                                shield_overrides(decision, env.actions))
        _, _, terminated, truncated, info = env.step(action)
        if recorder is not None:
            recorder.steps(info['step_results'])
        done = terminated or truncated
    if recorder is not None:
        recorder.finish()
    return env.episode_log.metrics()


def command_steps(env: ExitDecisionEnv, commands_of: Callable[[ExitDecisionEnv], dict], seed: int) -> Iterator[dict]:
    """Plays one episode whose CAVs get off-grid commands: ``commands_of(env)`` gives them at
    every decision step (vehicle id -> ``CavCommand``; the options' low level); yields each
    decision step's info (its ``step_results``: every simulation step's vehicles)."""
    env.reset(seed=seed)
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step_commands(commands_of(env))
        done = terminated or truncated
        yield info


def run_commands_episode(env: ExitDecisionEnv, commands_of: Callable[[ExitDecisionEnv], dict], seed: int,
                         ) -> dict[str, float]:
    """``command_steps``' episode played to its end: its metrics."""
    for _ in command_steps(env, commands_of, seed):
        pass
    return env.episode_log.metrics()


#: picks an option for a CAV whose option ended: (vehicle, its option mask) -> option index
OptionChooser = Callable[[VehicleState, np.ndarray], int]


def constant_option(index: int) -> Callable[[ExitDecisionEnv], OptionChooser]:
    """``run_option_episode``'s chooser of a constant option (a fixed driver of the low level)."""
    return lambda env: lambda vehicle, mask: index


def run_option_episode(env: ExitDecisionEnv, executor: OptionExecutor,
                       chooser_at: Callable[[ExitDecisionEnv], OptionChooser], seed: int) -> dict[str, float]:
    """One episode with options: at every decision step ``chooser_at(env)`` gives the chooser of
    that decision (a policy's Q values are computed once per decision), each CAV whose option
    ended gets a new one from it, and the held options become the CAVs' commands."""
    executor.reset()

    def commands_of(env: ExitDecisionEnv) -> dict:
        snapshot, cav_ids = env.sim.snapshot, env.graph.cav_ids()
        executor.choose(snapshot, cav_ids, env.sim.state.time, chooser_at(env))
        return executor.commands(snapshot, cav_ids)

    return run_commands_episode(env, commands_of, seed)


def run_option_policy(env: ExitDecisionEnv, controller: PolicyController, weights: np.ndarray | None,
                      seeds: Sequence[int], desc: str | None = None) -> list[dict]:
    """A policy over options on the seeds (``run_episodes``' rows), driven as the decision node
    and replay drive it (``model.driving.PolicyDriver``)."""
    controller.network_weights(weights)   # refused now, not at the first decision
    driver = PolicyDriver(controller, env.config)
    out = []
    for seed in tqdm(seeds, desc=desc, unit='ep', disable=desc is None):
        driver.reset()
        metrics = run_commands_episode(
            env, lambda env: driver.decide(env.graph, env.sim.snapshot, weights, env.sim.state.time).commands, seed)
        out.append({'seed': seed, **metrics, 'reward_vector': env.episode_log.reward_vector.copy()})
    return out


def play_policy(env: ExitDecisionEnv, controller: PolicyController, weights: np.ndarray | None, seeds: Sequence[int],
                desc: str | None = None, result: EvaluationResult | None = None,
                show: ShowEpisodes | None = None) -> list[dict]:
    """A policy's episodes at ``weights`` (``run_episodes``' rows), whichever its action space:
    over options through the low level (``run_option_policy``), on the grid as a driver."""
    if controller.policy.action_space == 'options':
        return run_option_policy(env, controller, weights, seeds, desc)
    return run_episodes(env, controller.at(weights), seeds, result, desc=desc, show=show)


def run_episodes(env: ExitDecisionEnv, controller: Controller | None, seeds: Sequence[int],
                 result: EvaluationResult | None = None, desc: str | None = None,
                 show: ShowEpisodes | None = None) -> list[dict]:
    """Per seed: the episode's metrics and its reward vector (to score it under any mode);
    ``result`` collects action counts and shield overrides; ``desc``: a progress bar; ``show``:
    draw the first episodes."""
    result = result if result is not None else EvaluationResult()
    out = []
    for index, seed in enumerate(tqdm(seeds, desc=desc, unit='ep', disable=desc is None)):
        metrics = run_episode(env, controller, seed, result, show and show.recorder(index, seed))
        out.append({'seed': seed, **metrics, 'reward_vector': env.episode_log.reward_vector.copy()})
    return out


@dataclass
class EvaluatedRun:
    """A run's episodes under one scoring mode (a conditioned policy: acting at that mode)."""
    label: str                  # <run>_<mode>
    episodes: list[dict]
    result: EvaluationResult


def scored_episodes(episodes: list[dict], weights) -> list[dict]:
    """Per-episode rows with ``reward`` = the episode's global scalar return under weights."""
    return [{**{k: v for k, v in e.items() if k != 'reward_vector'}, 'reward': float(scalar(e['reward_vector'], weights))}
            for e in episodes]


def evaluate_policy(env: ExitDecisionEnv, path: Path | str, modes: Sequence[str], seeds: list[int],
                    show: ShowEpisodes | None = None, name: str | None = None) -> list[EvaluatedRun]:
    """The policy at ``path`` on the seeds, scored under each mode: a conditioned one acts at
    each mode's weights, a per-mode one acts once (for its own mode). ``name``: the run's
    (default <algorithm>_<mode> of the checkpoint)."""
    config = env.config
    controller = load_controller(config, path, env.shield, env.planner, action_spaces=('grid', 'options'))
    policy, modes_weights = controller.policy, ModeWeights(config)
    if policy.action_space == 'options' and show is not None:
        raise PolicyError(f'{policy.path}: --show draws grid policies only (not yet a policy over options)')
    name = name or policy.run_name
    runs, played, result = [], None, None
    for mode in modes:
        if policy.conditioned or played is None:
            result = EvaluationResult()
            weights = modes_weights.weights(mode) if policy.conditioned else None
            desc = f'{name} at {mode}' if policy.conditioned else name
            played = play_policy(env, controller, weights, seeds, desc, result,
                                 show and show.named(f'{name}_{mode}' if policy.conditioned else name,
                                                     mode if policy.conditioned else policy.metadata['mode']))
        runs.append(EvaluatedRun(f'{name}_{mode}', scored_episodes(played, env.reward_fn.weights(config.mode(mode))), result))
    return runs
