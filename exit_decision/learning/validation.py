"""Validation of training checkpoints against the teacher, on the same validation seeds.

A candidate runs greedily on the validation seeds in every validation mode (a conditioned
policy at each mode's weights; a per-mode policy once, scored under its mode). Each mode's
row holds its safety figures and the mean paired return gain over the teacher on the same
seeds: the neutral rule-based driver for a grid policy, the best fixed driver of the mode (the
best constant option) for a policy over options (the teacher's runs are made once per process
and scored under every mode from their reward vectors). ``selection_score`` turns the rows into the number
the trainer keeps the best checkpoint by (``record_validation``). ``Validator`` runs the
validations in a second process (``validation.parallel``) while training goes on, so both
cores work.
"""
from __future__ import annotations

import csv
import multiprocessing
import shutil
from concurrent.futures import Future, ProcessPoolExecutor
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from exit_decision.config.seeds import VALIDATION_SEED
from exit_decision.config import ProjectConfig, ValidationConfig
from exit_decision.evaluation.statistics import paired_difference
from exit_decision.tables import append_row

if TYPE_CHECKING:
    from exit_decision.env import ExitDecisionEnv

INFEASIBLE = -1000.0   # score offset of a candidate outside the safety targets in some mode


def validation_seeds(episodes: int) -> list[int]:
    """The seeds every candidate (and the teacher) is validated on."""
    return [VALIDATION_SEED + i for i in range(episodes)]


@dataclass(frozen=True)
class ValidationTask:
    config: ProjectConfig
    modes: list[str]
    seeds: list[int]
    action_space: str = 'grid'   # options: the teacher is the best fixed driver of each mode
    #: over options, the constant options' episodes on ``seeds`` when the caller played them
    #: already (the trainer, measuring its prior); None: validation plays them
    style_episodes: Mapping[str, list[dict]] | None = None


_worker: dict = {}   # per process: the env and the teacher's episodes (libsumo: one simulation per process)


def _teacher_episodes(task: ValidationTask, env) -> dict[str, list[dict]]:
    """Per validation mode, the episodes of the driver a candidate is judged against: the
    neutral rule-based driver on the grid; over options, the best fixed driver of that mode
    (the constant option, one style on the route's lane plan, of highest mean return)."""
    from exit_decision.driving import fixed
    from exit_decision.evaluation.evaluate import (best_fixed_driver, constant_option_episodes, play_episodes,
                                                   scored_episodes)

    if task.action_space == 'grid':
        return dict.fromkeys(task.modes, play_episodes(env, fixed.rule_based(env), task.seeds))
    by_style = task.style_episodes or constant_option_episodes(env, task.seeds)

    def best(mode: str) -> list[dict]:
        weights = env.reward_fn.weights(task.config.mode(mode))
        return by_style[best_fixed_driver({style: [e['reward'] for e in scored_episodes(episodes, weights)]
                                           for style, episodes in by_style.items()})]
    return {mode: best(mode) for mode in task.modes}


def _env_and_teacher(task: ValidationTask, env=None):
    from exit_decision.env import ExitDecisionEnv

    if env is None:
        if 'env' not in _worker:
            _worker['env'] = ExitDecisionEnv(task.config, mode=task.modes[0])
        env = _worker['env']
    key = (tuple(task.seeds), id(env), task.config.model_dump_json(), task.action_space)   # another run: another teacher
    if _worker.get('teacher_seeds') != key:
        _worker['teacher'] = _teacher_episodes(task, env)
        _worker['teacher_seeds'] = key
    return env, _worker['teacher']


def validate_checkpoint(task: ValidationTask, path: Path, env=None) -> dict[str, dict[str, float]]:
    """Per validation mode: mean metrics of the candidate, its return and the teacher's, and
    the paired gain with its 95% interval. ``env``: the caller's (inline validation; a
    worker process makes its own)."""
    from exit_decision.evaluation.evaluate import evaluate_policy, scored_episodes

    env, teacher = _env_and_teacher(task, env)
    max_steps = task.config.scenario.max_steps
    out = {}
    for run, mode in zip(evaluate_policy(env, path, task.modes, task.seeds), task.modes):
        theirs = scored_episodes(teacher[mode], env.reward_fn.weights(task.config.mode(mode)))
        own = np.array([e['reward'] for e in run.episodes])
        gain, low, high = paired_difference(run.episodes, theirs, 'reward')
        out[mode] = {
            **{k: float(np.nanmean([e[k] for e in run.episodes])) for k in ('p_CAV', 'p_collision_CAV', 'v_AVs', 'N_braking')},
            'capped': float(sum(e['steps'] >= max_steps for e in run.episodes)),
            'return': float(own.mean()), 'teacher_return': float(np.mean([e['reward'] for e in theirs])),
            'teacher_p_CAV': float(np.nanmean([e['p_CAV'] for e in theirs])),
            'gain': gain, 'gain_low': low, 'gain_high': high,
            # over options with a prior: the share of options begun that are not the prior's
            'departures': run.result.departures / run.result.choices if run.result.choices else float('nan')}
    return out


def selection_score(per_mode: dict[str, dict[str, float]], min_exit_rate: float, max_cav_collision_rate: float) -> float:
    """The smallest mean gain over the teacher across the modes when every mode meets the
    safety targets (exit rate, CAV collision rate, no capped episode); otherwise far below
    any feasible score, ranked by the worst shortfall."""
    shortfall = max(max(min_exit_rate - row['p_CAV'], row['p_collision_CAV'] - max_cav_collision_rate,
                        row['capped']) for row in per_mode.values())
    gain = min(row['gain'] for row in per_mode.values())
    return gain if shortfall <= 0 else INFEASIBLE - shortfall


def record_validation(out_dir: Path, path: Path, per_mode: dict[str, dict[str, float]], settings: ValidationConfig,
                      best_score: float) -> float:
    """Log the validation of the candidate at ``path`` in validation.csv and keep it as
    policy.pt when its score beats ``best_score``; returns the best score."""
    score = selection_score(per_mode, settings.min_exit_rate, settings.max_cav_collision_rate)
    episode = candidate_episode(path)
    for mode, row in per_mode.items():
        append_row(out_dir / 'validation.csv', {'episode': episode, 'mode': mode, **row, 'score': score})
    if score > best_score:
        shutil.copyfile(path, out_dir / 'policy.pt')
        return score
    return best_score


def candidate_episode(path: Path) -> int:
    """The training episode a candidate was saved after (candidates/episode_<n>.pt)."""
    return int(path.stem.split('_')[1])


def validated_scores(out_dir: Path) -> dict[int, float]:
    """Per candidate episode in the run's validation.csv, its selection score."""
    log = out_dir / 'validation.csv'
    if not log.exists():
        return {}
    with open(log, newline='') as stream:
        return {int(row['episode']): float(row['score']) for row in csv.DictReader(stream)}


def unvalidated_candidates(out_dir: Path) -> list[Path]:
    """The run's candidates without a row in validation.csv, oldest first: those a stopped run
    saved but did not validate (its validation process ends with it); a resumed run validates them."""
    done = validated_scores(out_dir)
    return [path for path in sorted((out_dir / 'candidates').glob('episode_*.pt')) if candidate_episode(path) not in done]


class Validator:
    """Runs candidate validations in a second process (or inline, in the trainer's ``env``),
    their results in submission order."""

    def __init__(self, task: ValidationTask, parallel: bool, env: ExitDecisionEnv):
        self.task, self.env = task, env
        self.pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('spawn')) if parallel else None
        self.pending: list[tuple[Path, Future | dict]] = []

    def __enter__(self) -> Validator:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)

    def submit(self, path: Path) -> None:
        """Validate the candidate at ``path``: in the second process, or at once here (every CAV
        driven by the candidate, SGRL's one-at-a-time training env too)."""
        if self.pool is None:
            single, self.env.sim.single_agent = self.env.sim.single_agent, False   # validated driving every CAV
            try:
                self.pending.append((path, validate_checkpoint(self.task, path, self.env)))
            finally:
                self.env.sim.single_agent = single
        else:
            self.pending.append((path, self.pool.submit(validate_checkpoint, self.task, path)))

    def finished(self, wait: bool = False) -> list[tuple[Path, dict]]:
        """The validations done (``wait``: all of them, waiting), oldest first."""
        done = []
        while self.pending:
            path, result = self.pending[0]
            if isinstance(result, Future):
                if not (wait or result.done()):
                    break
                result = result.result()
            done.append((path, result))
            self.pending.pop(0)
        return done
