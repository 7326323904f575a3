"""The reward sanity sweep: does each mode's reward prefer what the mode names?

Rule-based drivers that differ from the neutral one in one setting (config/reward_sanity.yaml)
drive the same seeds, on the action grid or (``low_level='options'``) with the options' low
level (env.yaml ``options.low_level``, off the grid: the drivers a policy over options chooses
among); every episode's reward vector (``exit_decision.reward``) is scored under
every mode and every reward variant asked for. The table gives, per mode, each driver's
return minus the neutral driver's on the same seeds where neither collided (the safe set;
mean and paired 95% interval), with the driver's speed, exits, collisions and hard braking.
Before any training, it shows whether faster safe driving pays in the aggressive modes and
larger gaps in the conservative ones.

``calibrate`` searches multipliers of the row scales (from the recorded episodes, no
simulation) for the calibration under which the expected orderings of the sweep file hold
most clearly: the largest smallest t statistic over the expected (driver, mode) pairs.
"""
from __future__ import annotations

import itertools
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict
from tqdm import tqdm

from exit_decision.config import ConfigError, ProjectConfig, RuleBasedConfig, load_yaml, parse
from exit_decision.evaluation.statistics import paired_interval
from exit_decision.reward import ROWS, VECTOR_COLUMNS, make_reward, scalar
from exit_decision.tables import write_rows


#: how the sweep's drivers drive: on the action grid, or off it with the options' low level
LowLevel = Literal['grid', 'options']


class SweepConfig(BaseModel):
    model_config = ConfigDict(extra='forbid')
    neutral: str
    drivers: dict[str, dict[str, float]]
    expect: dict[str, dict[str, Literal[-1, 1]]]


def load_sweep(path: Path, config: ProjectConfig) -> tuple[dict[str, RuleBasedConfig], dict[str, dict[str, int]]]:
    """The drivers of a sweep file (the neutral one first), each validated over env.yaml's
    rule_based, and the expected orderings; errors name the key."""
    sweep = parse(SweepConfig, load_yaml(path), path)
    if sweep.neutral not in sweep.drivers:
        raise ConfigError(f'{path}: neutral: {sweep.neutral!r} is not one of the drivers ({", ".join(sweep.drivers)})')
    for driver, modes in sweep.expect.items():
        if driver not in sweep.drivers:
            raise ConfigError(f'{path}: expect.{driver}: not one of the drivers ({", ".join(sweep.drivers)})')
        for mode in modes:
            config.mode(mode)
    base = config.env.rule_based.model_dump()
    drivers = {name: parse(RuleBasedConfig, {**base, **keys}, f'{path} drivers.{name}')
               for name, keys in sweep.drivers.items()}
    return {sweep.neutral: drivers.pop(sweep.neutral), **drivers}, sweep.expect


def _episode(task: tuple) -> list[dict]:
    """One driver on one seed (in a worker process: libsumo is one simulation per process)."""
    config, name, parameters, seed, variants, low_level = task
    from exit_decision.driving import fixed
    from exit_decision.driving.episode import play_episode

    env = _worker_env(config, variants[0])
    driver = fixed.rule_based_low_level(env, parameters.model_copy(update=config.env.options.low_level)) \
        if low_level == 'options' else fixed.rule_based(env, parameters)
    metrics = play_episode(env, driver, seed)
    return variant_rows(config, env, variants, {'driver': name, 'seed': seed}, metrics)


def variant_rows(config: ProjectConfig, env, variants: list[str], key: dict, metrics: dict) -> list[dict]:
    """One row per reward variant of the episode just run in ``env`` (made with
    ``keep_step_inputs``): its steps scored again under the variant, the rows' sums and the
    return under every mode."""
    rows = []
    for variant in variants:
        reward = make_reward(config.reward(variant), config.scenario.step_length,
                             config.scenario.emergency_braking_threshold)
        vector = sum((reward.vector(inputs).total() for inputs in env.step_inputs), np.zeros((4, 2)))
        row = {**key, 'variant': variant, **metrics}
        row.update(zip(VECTOR_COLUMNS, vector.ravel()))
        row.update({f'return_{mode}': float(scalar(vector, reward.weights(config.mode(mode)))) for mode in config.modes})
        rows.append(row)
    return rows


_ENV = None


def _worker_env(config: ProjectConfig, variant: str):
    from exit_decision.env import ExitDecisionEnv
    global _ENV
    if _ENV is None:
        _ENV = ExitDecisionEnv(config, reward_variant=variant, keep_step_inputs=True)
    return _ENV


def run_sweep(config: ProjectConfig, drivers: dict[str, RuleBasedConfig], seeds: list[int],
              variants: list[str], jobs: int, low_level: LowLevel = 'grid') -> list[dict]:
    tasks = [(config, name, parameters, seed, variants, low_level)
             for name, parameters in drivers.items() for seed in seeds]
    rows: list[dict] = []
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        for result in tqdm(pool.map(_episode, tasks, chunksize=4), total=len(tasks), desc='reward sanity',
                           unit='ep'):
            rows += result
    return rows


def _by_driver_and_seed(rows: list[dict], variant: str) -> dict[tuple[str, int], dict]:
    return {(r['driver'], int(r['seed'])): r for r in rows if r['variant'] == variant}


def safe_seeds(by: dict[tuple[str, int], dict], driver: str, neutral: str) -> list[int]:
    """Seeds on which neither the driver nor the neutral one had any collision."""
    return sorted(s for d, s in by if d == neutral and (driver, s) in by
                  and float(by[(driver, s)]['p_collision']) == 0 and float(by[(neutral, s)]['p_collision']) == 0)


def sanity_table(rows: list[dict], modes: list[str], neutral: str, variant: str) -> str:
    """Markdown: per mode, each driver's return minus the neutral driver's (paired over the
    seeds where neither collided); speed and safety columns over all seeds."""
    by = _by_driver_and_seed(rows, variant)
    drivers = list(dict.fromkeys(d for d, _ in by))
    seeds = sorted(s for d, s in by if d == neutral)
    lines = [f'### Reward variant `{variant}` ({len(seeds)} seeds)', '',
             '| driver | v_AVs | p_CAV | p_collision_CAV | N_braking | safe seeds | '
             + ' | '.join(f'{m}: return − neutral' for m in modes) + ' |',
             '|---' * (6 + len(modes)) + '|']
    for driver in drivers:
        own = [by[(driver, s)] for s in seeds]
        cells = [f'{np.mean([float(r[k]) for r in own]):.3g}' for k in ('v_AVs', 'p_CAV', 'p_collision_CAV', 'N_braking')]
        safe = safe_seeds(by, driver, neutral)
        cells.append(str(len(safe)))
        for mode in modes:
            if driver == neutral:
                cells.append(f'{np.mean([float(by[(driver, s)][f"return_{mode}"]) for s in safe]):.3f} (level)')
                continue
            diff = [float(by[(driver, s)][f'return_{mode}']) - float(by[(neutral, s)][f'return_{mode}']) for s in safe]
            mean, low, high = paired_interval(diff)
            mark = ' ↑' if low > 0 else ' ↓' if high < 0 else ''
            cells.append(f'{mean:+.3f} [{low:+.3f}, {high:+.3f}]{mark}')
        lines.append(f'| {driver} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


CALIBRATION_GRID = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0)


def calibrate(rows: list[dict], config: ProjectConfig, variant: str, neutral: str,
              expect: dict[str, dict[str, int]], top: int = 5) -> str:
    """Multipliers m of the efficiency, comfort and safety rows (scales divided by m) under
    which the expected orderings hold most clearly; the recorded vectors are rescaled."""
    by = _by_driver_and_seed(rows, variant)
    columns = list(VECTOR_COLUMNS)
    vector = {key: np.array([float(row[c]) for c in columns]).reshape(4, 2) for key, row in by.items()}
    reward = make_reward(config.reward(variant), config.scenario.step_length)
    pairs = []
    for driver, modes in expect.items():
        seeds = safe_seeds(by, driver, neutral)
        deltas = np.array([vector[(driver, s)] - vector[(neutral, s)] for s in seeds])   # (S, 4, 2)
        pairs += [(driver, mode, sign, deltas, reward.weights(config.mode(mode))) for mode, sign in modes.items()]
    results = []
    for m in itertools.product([1.0], CALIBRATION_GRID, CALIBRATION_GRID, CALIBRATION_GRID):
        multiplier = np.array(m)[:, None]
        t = []
        for _, _, sign, deltas, weights in pairs:
            diff = sign * (deltas * multiplier * weights).sum(axis=(1, 2))
            t.append(diff.mean() / (diff.std(ddof=1) / np.sqrt(len(diff))))
        results.append((min(t), m))
    results.sort(key=lambda item: -item[0])
    scales = np.array([getattr(reward.config.scales, r) for r in ROWS])
    lines = [f'Calibration of `{variant}` ({len(pairs)} expected orderings; rows result, efficiency, comfort, safety):',
             '| smallest t | multipliers | scales |', '|---|---|---|']
    for t_min, m in results[:top]:
        lines.append(f'| {t_min:.2f} | {", ".join(f"{x:g}" for x in m)} | '
                     f'{", ".join(f"{x:.0f}" for x in scales / np.array(m))} |')
    return '\n'.join(lines)


def write_sanity(config: ProjectConfig, sweep_file: Path, seeds: list[int], variants: list[str], jobs: int,
                 out_dir: Path, command: str, low_level: LowLevel = 'grid') -> str:
    drivers, _ = load_sweep(sweep_file, config)
    for variant in variants:
        config.reward(variant)
    rows = run_sweep(config, drivers, seeds, variants, jobs, low_level)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_rows(out_dir / 'episodes.csv', rows)
    modes = list(config.modes)
    neutral = next(iter(drivers))
    tables = [sanity_table(rows, modes, neutral, variant) for variant in variants]
    text = (f'# Reward sanity: rule-based drivers scored under every mode\n\nMade by `{command}` '
            f'(seeds {seeds[0]}..{seeds[-1]}); per-episode rows in `episodes.csv`. Each cell: the '
            f'driver\'s episode return minus the neutral driver\'s on the same seed, over the seeds where '
            f'neither had a collision ("safe seeds"), mean and paired 95% interval (↑ / ↓: the interval '
            f'excludes 0). Speed and safety columns: all seeds. Drivers: `{sweep_file.name}`.\n\n'
            + '\n\n'.join(tables) + '\n')
    (out_dir / 'reward_sanity.md').write_text(text, encoding='utf-8')
    return text
