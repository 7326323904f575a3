"""The constant-option table (issue 28): every constant option under every mode, on the same seeds.

A constant option is one style for every CAV, held for the whole episode, with the lane
intent ``route`` (the route's lane plan, as the rule-based driver's): a fixed driver of the
options' low level. Per mode, the best of them is "the best fixed driver" a learned options policy
must beat. Beside them, as references on the same seeds: the grid's neutral rule-based driver
(the old teacher) and SUMO's own drivers. Every run's episodes are scored under every mode
from their reward vectors (``exit_decision.reward``), so one episode per run and seed is
enough. One simulation per worker process (libsumo).
"""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor

import numpy as np
from tqdm import tqdm

from exit_decision.config import ProjectConfig
from exit_decision.evaluation.statistics import paired_interval
from exit_decision.reward import scalar

#: the references beside the options' styles (run name -> how its CAVs are driven)
REFERENCES = ('grid_rule_based', 'sumo')
COLUMNS = ('v_AVs', 'headway_CAV', 'N_braking_CAV', 'N_braking', 'p_CAV', 'p_collision_CAV')


def option_run_name(style: str) -> str:
    return f'option_{style}'


def _episode(task: tuple) -> dict:
    """One run on one seed, in a worker process; the row holds its return under every mode."""
    config, run, seed = task
    from exit_decision.agents.options import OptionExecutor, OptionSpace
    from exit_decision.agents.rule_based import RuleBasedDriver
    from exit_decision.evaluation.evaluate import EvaluationResult, run_episode

    env = _worker_env(config, 'sumo' if run == 'sumo' else 'policy')
    if run == 'sumo':
        metrics = run_episode(env, None, seed, EvaluationResult())
    elif run == 'grid_rule_based':
        metrics = run_episode(env, RuleBasedDriver.for_env(env), seed, EvaluationResult())
    else:
        space = OptionSpace(config, env.shield, env.planner)
        constant = space.index('route', run.removeprefix('option_'))
        executor = OptionExecutor(space)
        metrics = run_option_episode(env, executor, lambda vehicle, mask: constant, seed)
    vector = env.episode_log.reward_vector
    row = {'run': run, 'seed': seed, **metrics}
    row.update({f'return_{mode}': float(scalar(vector, env.reward_fn.weights(config.mode(mode))))
                for mode in config.modes})
    return row


def run_option_episode(env, executor, chooser, seed: int) -> dict[str, float]:
    """One episode with options: at every decision step each CAV whose option ended gets a new
    one from ``chooser(vehicle, mask)``, and the held options become the CAVs' commands."""
    env.reset(seed=seed)
    executor.reset()
    done = False
    while not done:
        snapshot, cav_ids = env.sim.snapshot, env.graph.cav_ids()
        executor.choose(snapshot, cav_ids, env.sim.state.time, chooser)
        _, _, terminated, truncated, _ = env.step_commands(executor.commands(snapshot, cav_ids))
        done = terminated or truncated
    return env.episode_log.metrics()


_ENV = None


def _worker_env(config: ProjectConfig, cav_driver: str):
    """The worker's one environment (libsumo: one simulation per process), made again when
    the CAVs' driver changes."""
    from exit_decision.env import ExitDecisionEnv
    global _ENV
    if _ENV is None or _ENV.sim.cav_driver != cav_driver:
        if _ENV is not None:
            _ENV.close()
        _ENV = ExitDecisionEnv(config, cav_driver=cav_driver)
    return _ENV


def run_table(config: ProjectConfig, seeds: list[int], jobs: int) -> list[dict]:
    runs = [option_run_name(style) for style in config.env.options.styles] + list(REFERENCES)
    tasks = [(config, run, seed) for run in runs for seed in seeds]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        return list(tqdm(pool.map(_episode, tasks, chunksize=4), total=len(tasks), desc='constant options',
                         unit='ep'))


def table_markdown(rows: list[dict], modes: list[str], neutral: str = option_run_name('neutral')) -> str:
    """Per run: the driving columns, then per mode its return and the paired difference to the
    neutral option; then, per mode, the best constant option (the best fixed driver)."""
    runs = list(dict.fromkeys(r['run'] for r in rows))
    by = {(r['run'], int(r['seed'])): r for r in rows}
    seeds = sorted(s for run, s in by if run == neutral)
    lines = ['| run | ' + ' | '.join(COLUMNS) + ' | ' + ' | '.join(f'{m}: return (− neutral option)' for m in modes)
             + ' |', '|---' * (1 + len(COLUMNS) + len(modes)) + '|']
    best = {}
    for run in runs:
        episodes = [by[(run, s)] for s in seeds]
        cells = [f'{np.nanmean([float(e[c]) for e in episodes]):.3g}' for c in COLUMNS]
        for mode in modes:
            values = np.array([float(e[f'return_{mode}']) for e in episodes])
            mean, low, high = paired_interval(values - [float(by[(neutral, s)][f'return_{mode}']) for s in seeds])
            mark = ' ↑' if low > 0 else ' ↓' if high < 0 else ''
            cells.append(f'{values.mean():.3f} ({mean:+.3f} [{low:+.3f}, {high:+.3f}]{mark})')
            if run.startswith('option_') and (mode not in best or values.mean() > best[mode][1]):
                best[mode] = (run, values.mean())
        lines.append(f'| {run} | ' + ' | '.join(cells) + ' |')
    lines += ['', 'The best fixed driver (the best constant option) per mode: '
              + ', '.join(f'{mode} `{run}` ({value:.3f})' for mode, (run, value) in best.items()) + '.']
    return '\n'.join(lines)
