"""Evaluation runs: a driver (``driving``) on fixed seeds, metrics per episode, scored under modes."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from exit_decision.agents.options import OptionSpace
from exit_decision.driving import fixed
from exit_decision.driving.episode import play_episode
from exit_decision.driving.interface import Driver, StepDecision
from exit_decision.driving.policy import own_mode, policy_driver
from exit_decision.driving.prior import PriorTable
from exit_decision.env import ExitDecisionEnv
from exit_decision.errors import PolicyError
from exit_decision.model.modes import ModeWeights
from exit_decision.model.policy import load_controller
from exit_decision.reward import scalar
from exit_decision.visualization.episodes import ShowEpisodes


@dataclass
class EvaluationResult:
    """What a run chose: on the grid its actions and the shield's refusals; over options, given
    the prior's option (``prior_option``), how often a CAV began another (``driving.prior``)."""
    action_counts: np.ndarray | None = None   # how often each action of the grid was chosen
    overrides: int = 0                         # first choices the shield refused
    decisions: int = 0                         # CAV decisions made
    prior_option: int | None = None            # over options: the prior's option at the run's mode
    choices: int = 0                           # over options: options begun
    departures: int = 0                        # over options: options begun that are not the prior's

    def add(self, decision: StepDecision, grid_size: int) -> None:
        if decision.options is not None:
            if self.prior_option is not None:
                self.choices += len(decision.began)
                self.departures += sum(decision.actions[v] != self.prior_option for v in decision.began)
            return
        if not decision.actions:
            return
        if self.action_counts is None:
            self.action_counts = np.zeros(grid_size, dtype=np.int64)
        for index in decision.actions.values():
            self.action_counts[index] += 1
        self.overrides += len(decision.overrides)
        self.decisions += len(decision.actions)


def play_episodes(env: ExitDecisionEnv, driver: Driver, seeds: Sequence[int], result: EvaluationResult | None = None,
                  desc: str | None = None, show: ShowEpisodes | None = None) -> list[dict]:
    """Per seed: the episode's metrics and its reward vector (to score it under any mode);
    ``result`` collects the grid's action counts and shield overrides; ``desc``: a progress bar;
    ``show``: draw the first episodes."""
    result = result if result is not None else EvaluationResult()
    out = []
    for index, seed in enumerate(tqdm(seeds, desc=desc, unit='ep', disable=desc is None)):
        recorder = show and show.recorder(index, seed)

        def on_step(decision: StepDecision, info: dict, terminated: bool, truncated: bool) -> None:
            result.add(decision, env.actions.size)
            if recorder is not None:
                recorder.decide(decision.commands, decision.overrides)
                recorder.steps(info['step_results'])

        metrics = play_episode(env, driver, seed, on_step, recorder and (lambda: recorder.start(env)))
        if recorder is not None:
            recorder.finish()
        out.append({'seed': seed, **metrics, 'reward_vector': env.episode_log.reward_vector.copy()})
    return out


def best_fixed_driver(returns: Mapping[str, Sequence[float]]) -> str:
    """The fixed driver (by name) of highest mean return on the same seeds, the first on a tie:
    the best fixed driver a learned policy over options must beat (validation and the tables)."""
    return max(returns, key=lambda name: float(np.mean(returns[name])))


def constant_option_episodes(env: ExitDecisionEnv, seeds: Sequence[int], desc: str | None = None) -> dict[str, list[dict]]:
    """Every style of config/env.yaml's options as a constant option on ``seeds``: its episodes
    (what the prior is measured from, and validation's best fixed driver chosen from)."""
    space = OptionSpace(env.config, env.shield, env.planner)
    return {style: play_episodes(env, fixed.constant_option(space, style), seeds, desc=desc and f'{desc}: {style}')
            for style in env.config.env.options.styles}


def prior_of(env: ExitDecisionEnv, by_style: Mapping[str, list[dict]]) -> PriorTable:
    """The prior's table (``driving.prior``) of the constant options' episodes: each style's mean
    reward vector under ``env``'s scoring variant."""
    seeds = tuple(e['seed'] for e in next(iter(by_style.values())))
    return PriorTable(env.reward_variant, seeds,
                      {style: np.mean([e['reward_vector'] for e in episodes], axis=0) for style, episodes in by_style.items()})


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


def prior_option(policy, env: ExitDecisionEnv, mode) -> int | None:
    """The option of the prior a policy over options carries (``GraphPolicy.prior``) at ``mode``;
    None on the grid or without a prior."""
    if policy.action_space != 'options' or policy.prior is None:
        return None
    table = PriorTable.from_metadata(policy.prior)
    return table.best_option(OptionSpace(env.config, env.shield, env.planner), mode.weights)


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
    driver = policy_driver(controller, config)
    runs, played, result = [], None, None
    for mode in modes:
        if policy.conditioned or played is None:
            driver.set_mode(own_mode(controller, modes_weights, mode))
            result = EvaluationResult(prior_option=prior_option(policy, env, driver.mode))
            desc = f'{name} at {mode}' if policy.conditioned else name
            played = play_episodes(env, driver, seeds, result, desc,
                                   show and show.named(f'{name}_{mode}' if policy.conditioned else name, driver.mode.name))
        runs.append(EvaluatedRun(f'{name}_{mode}', scored_episodes(played, env.reward_fn.weights(config.mode(mode))), result))
    return runs
