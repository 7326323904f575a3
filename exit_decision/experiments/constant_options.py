"""The constant-option table (issue 28): every constant option under every mode, on the same seeds.

A constant option is one style for every CAV, held for the whole episode, with the lane
intent ``route`` (the route's lane plan, as the rule-based driver's): a fixed driver of the
options' low level. Per mode, the best of them is "the best fixed driver" a learned options policy
must beat. Beside them, as references on the same seeds: the grid's neutral rule-based driver
(the old teacher) and SUMO's own drivers. Every run's episodes are scored under every mode
from their reward vectors (``exit_decision.reward``), so one episode per run and seed is
enough, and under every reward variant asked for. One simulation per worker process (libsumo).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from exit_decision.config import ProjectConfig
from exit_decision.driving import fixed
from exit_decision.evaluation.evaluate import best_fixed_driver
from exit_decision.evaluation.statistics import paired_interval
from exit_decision.experiments.reward_sanity import variant_rows
from exit_decision.tables import write_rows

#: the references beside the options' styles (run name -> how its CAVs are driven)
REFERENCES = (fixed.GRID_RULE_BASED, fixed.SUMO)
COLUMNS = ('v_AVs', 'headway_CAV', 'N_braking_CAV', 'N_braking', 'p_CAV', 'p_collision_CAV')


#: a policy's run at a mode is named ``<label>@<mode>``
AT = '@'


def option_run_name(style: str) -> str:
    return fixed.OPTION_PREFIX + style


def neutral_run(config: ProjectConfig) -> str:
    """The run of the neutral driver over options (the planner's style, config/env.yaml): the
    tables' reference."""
    return option_run_name(config.env.options.neutral_style)


def policy_label(path: Path) -> str:
    """A policy's name in the table: its run directory for a ``policy.pt``, else
    ``<run directory>:<file>`` (a candidate, ``last.pt``)."""
    path = Path(path)
    if path.stem == 'policy':
        return path.parent.name
    run = path.parent.parent if path.parent.name == 'candidates' else path.parent
    return f'{run.name}:{path.stem}'


def _episode(task: tuple) -> list[dict]:
    """One run on one seed, in a worker process: a row per reward variant, with the return
    under every mode."""
    config, run, seed, variants, policies = task
    from exit_decision.driving.episode import play_episode

    env = _worker_env(config, 'sumo' if run == fixed.SUMO else 'policy')
    metrics = play_episode(env, _worker_driver(env, run, policies), seed)
    return variant_rows(config, env, variants, {'run': run, 'seed': seed}, metrics)


_WORKER: dict = {}   # per process: its one environment, and the drivers made for it


def _worker_env(config: ProjectConfig, cav_driver: str):
    """The worker's one environment (libsumo: one simulation per process), made again when
    the CAVs' driver changes (its drivers with it)."""
    from exit_decision.env import ExitDecisionEnv
    env = _WORKER.get('env')
    if env is None or env.sim.cav_driver != cav_driver:
        if env is not None:
            env.close()
        _WORKER.clear()
        _WORKER['env'] = env = ExitDecisionEnv(config, cav_driver=cav_driver, keep_step_inputs=True)
    return env


def _worker_driver(env, run: str, policies: dict[str, Path]):
    """The driver of ``run`` (a fixed driver by its name, or ``<policy label>@<mode>``), made once
    per worker and environment (a policy's checkpoint is loaded once, its mode set per run)."""
    from exit_decision.driving.policy import own_mode, policy_driver
    from exit_decision.model.modes import ModeWeights
    from exit_decision.model.policy import ACTION_SPACES, load_controller

    label, _, mode = run.partition(AT)
    if label not in _WORKER:
        if mode:
            controller = load_controller(env.config, policies[label], env.shield, env.planner,
                                         action_spaces=ACTION_SPACES)
            _WORKER[label] = policy_driver(controller, env.config)
        else:
            _WORKER[label] = fixed.by_name(env, label)
    driver = _WORKER[label]
    if mode:
        driver.set_mode(own_mode(driver.source, ModeWeights(env.config), mode))
    return driver


def run_table(config: ProjectConfig, seeds: list[int], variants: list[str], jobs: int,
              policies: dict[str, Path] | None = None) -> list[dict]:
    """The rows of every run on every seed; ``policies`` (label -> checkpoint): also each of them
    at each mode of the matrix (``<label>@<mode>``: a conditioned one acts at the mode's weights)."""
    runs = [option_run_name(style) for style in config.env.options.styles] + list(REFERENCES)
    policies = policies or {}
    runs += [f'{label}{AT}{mode}' for label in policies for mode in config.mode_matrix.modes]
    tasks = [(config, run, seed, variants, policies) for run in runs for seed in seeds]
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        return [row for rows in tqdm(pool.map(_episode, tasks, chunksize=4), total=len(tasks),
                                     desc='constant options', unit='ep') for row in rows]


def _by_run_and_seed(rows: list[dict], variant: str, neutral: str) -> tuple[dict, list[int]]:
    """The rows of one reward variant by (run, seed), and the seeds the neutral option ran."""
    by = {(r['run'], int(r['seed'])): r for r in rows if r['variant'] == variant}
    return by, sorted(s for run, s in by if run == neutral)


def _returns(by: dict, run: str, seeds: list[int], mode: str) -> np.ndarray:
    return np.array([float(by[(run, s)][f'return_{mode}']) for s in seeds])


def _side(low: float, high: float) -> int:
    """+1 / -1 when a 95% interval lies above / below 0; 0: not resolved."""
    return 1 if low > 0 else -1 if high < 0 else 0


def _interval(by: dict, run: str, other: str, seeds: list[int], key: str) -> tuple[float, float, float]:
    """``run`` minus ``other`` in column ``key``, paired over the seeds: mean and 95% interval."""
    return paired_interval([float(by[(run, s)][key]) - float(by[(other, s)][key]) for s in seeds])


def _interval_text(by: dict, run: str, other: str, seeds: list[int], key: str, digits: int = 3) -> str:
    """``_interval`` as text (↑ / ↓: the interval excludes 0)."""
    mean, low, high = _interval(by, run, other, seeds, key)
    return f'{mean:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}]' + {1: ' ↑', -1: ' ↓', 0: ''}[_side(low, high)]


def _paired(by: dict, run: str, other: str, seeds: list[int], mode: str) -> str:
    """``run``'s return under ``mode`` minus ``other``'s, paired over the seeds, as text."""
    return _interval_text(by, run, other, seeds, f'return_{mode}')


def _mean(by: dict, run: str, seeds: list[int], metric: str) -> float:
    """A run's mean of one metric over the seeds (episodes without it, NaN, left out)."""
    return float(np.nanmean([float(by[(run, s)][metric]) for s in seeds]))


def _means(by: dict, run: str, seeds: list[int]) -> list[str]:
    return [f'{_mean(by, run, seeds, c):.3g}' for c in COLUMNS]


def best_fixed_drivers(by: dict, seeds: list[int], modes: list[str]) -> dict[str, str]:
    """Per mode, the constant option with the highest mean return: the best fixed driver."""
    options = [run for run in dict.fromkeys(run for run, _ in by) if run.startswith(fixed.OPTION_PREFIX)]
    return {mode: best_fixed_driver({run: _returns(by, run, seeds, mode) for run in options}) for mode in modes}


def table_markdown(rows: list[dict], modes: list[str], variant: str, neutral: str,
                   orderings: list[tuple[str, str]] = ()) -> str:
    """Per run: the driving columns, then per mode its return under ``variant`` and the paired
    difference to the neutral option; then, per mode, the best constant option (the best fixed
    driver); then each policy at each mode against the best fixed driver and SUMO's drivers, and
    for each (aggressive, conservative) pair of ``orderings`` whether it drives as they are named."""
    by, seeds = _by_run_and_seed(rows, variant, neutral)
    runs = [run for run in dict.fromkeys(run for run, _ in by) if AT not in run]
    lines = [f'### Reward variant `{variant}` ({len(seeds)} seeds)', '', '| run | ' + ' | '.join(COLUMNS) + ' | ' + ' | '.join(f'{m}: return (− neutral option)' for m in modes)
             + ' |', '|---' * (1 + len(COLUMNS) + len(modes)) + '|']
    for run in runs:
        cells = _means(by, run, seeds) + [f'{_returns(by, run, seeds, mode).mean():.3f} ({_paired(by, run, neutral, seeds, mode)})'
                                          for mode in modes]
        lines.append(f'| {run} | ' + ' | '.join(cells) + ' |')
    best = best_fixed_drivers(by, seeds, modes)
    lines += ['', 'The best fixed driver (the best constant option) per mode: '
              + ', '.join(f'{mode} `{run}` ({_returns(by, run, seeds, mode).mean():.3f})' for mode, run in best.items()) + '.']
    labels = list(dict.fromkeys(run.split(AT)[0] for run, _ in by if AT in run))
    if labels:
        lines += ['', '| policy | mode | ' + ' | '.join(COLUMNS) + ' | return | − the best fixed driver | − SUMO\'s drivers |',
                  '|---' * (5 + len(COLUMNS)) + '|']
        for label, mode in ((label, mode) for label in labels for mode in modes):
            run = f'{label}{AT}{mode}'
            cells = _means(by, run, seeds) + [f'{_returns(by, run, seeds, mode).mean():.3f}']
            cells += [_paired(by, run, other, seeds, mode) for other in (best[mode], 'sumo')]
            lines.append(f'| {label} | {mode} | ' + ' | '.join(cells) + ' |')
        lines += [line for label in labels for line in _orderings(by, seeds, label, orderings)]
    return '\n'.join(lines)


def _orderings(by: dict, seeds: list[int], label: str, orderings: list[tuple[str, str]]) -> list[str]:
    """Per (aggressive, conservative) pair: the policy's paired speed difference and time-headway
    difference between the two modes, and whether each is as the modes are named."""
    lines = []
    for fast, slow in orderings:
        cells = []
        for metric, sign, unit in (('v_AVs', 1, 'm/s'), ('headway_CAV', -1, 's')):
            pairs = [(float(by[(f'{label}{AT}{fast}', s)][metric]), float(by[(f'{label}{AT}{slow}', s)][metric]))
                     for s in seeds]
            mean, low, high = paired_interval([sign * (a - b) for a, b in pairs if np.isfinite(a) and np.isfinite(b)])
            verdict = {1: 'as named', -1: 'reversed', 0: 'not resolved'}[_side(low, high)]
            what = f'{fast} − {slow} speed' if sign > 0 else f'{slow} − {fast} time headway'
            cells.append(f'{what} {mean:+.3f} {unit} [{low:+.3f}, {high:+.3f}] ({verdict})')
        lines.append(f'- `{label}`: ' + '; '.join(cells))
    return ([''] + lines) if lines else []


#: the README's results table: what each row is called there, and its columns (name, metric, format)
README_DRIVERS = {'policy': 'the shipped policy', 'best': 'the best fixed driver', 'neutral': 'the neutral driver',
                  'sumo': "SUMO's drivers"}
README_COLUMNS = (('Exit-1', 'p_CAV', '.3f'), ('CAV collisions', 'p_collision_CAV', '.4f'), ('speed [m/s]', 'v_AVs', '.2f'),
                  ('time headway [s]', 'headway_CAV', '.2f'),
                  ("hard brakings per episode, the CAVs' own", 'N_braking_CAV', '.2f'),
                  ('hard brakings per episode, all vehicles', 'N_braking', '.2f'))
#: the reward variants of the options tables, one line each (config/reward.yaml has them whole)
VARIANTS = {'headway': "config/env.yaml's default: the reward matrix with every incentive per metre driven, the "
                       'safe-gaps incentive graded by the time headway kept',
            'calibrated': "the earlier results' reward: the same matrix with the safe-gaps incentive per step, "
                          'not graded by headway'}
_SIDES = {1: 'above', -1: 'below', 0: 'not resolved'}


def _readme_runs(by: dict, seeds: list[int], mode: str, policy: str, best: str, neutral: str) -> dict[str, str]:
    """The README's rows under ``mode`` (role -> run): the policy's (when the rows hold it), the best
    fixed driver, the neutral driver (when it is not the best) and SUMO's drivers."""
    runs = {'policy': f'{policy}{AT}{mode}', 'best': best, 'neutral': neutral, 'sumo': 'sumo'}
    return {role: run for role, run in runs.items()
            if (run, seeds[0]) in by and not (role == 'neutral' and best == neutral)}


def readme_table(rows: list[dict], modes: list[str], variant: str, policy: str, neutral: str,
                 links: Mapping[str, str] | None = None) -> str:
    """The README's results table: per mode, the policy labelled ``policy`` (when the rows hold
    it), the best fixed driver, the neutral driver and SUMO's drivers, with their means and the
    return's paired differences to the neutral and the best fixed driver; then the rows' reward
    variants, one line each, linked to their tables (``links``: variant -> URL)."""
    by, seeds = _by_run_and_seed(rows, variant, neutral)
    best = best_fixed_drivers(by, seeds, modes)
    lines = ['| mode | driver | ' + ' | '.join(name for name, _, _ in README_COLUMNS)
             + ' | return − the neutral driver [95%] | return − the best fixed driver [95%] |',
             '|---' * (4 + len(README_COLUMNS)) + '|']
    for mode in modes:
        for role, run in _readme_runs(by, seeds, mode, policy, best[mode], neutral).items():
            label = README_DRIVERS[role] + (f' (`{run.removeprefix("option_")}`'
                                            + (', the neutral driver)' if run == neutral else ')') if role == 'best' else '')
            cells = [format(_mean(by, run, seeds, metric), spec) for _, metric, spec in README_COLUMNS]
            cells += ['—' if run == other else _paired(by, run, other, seeds, mode) for other in (neutral, best[mode])]
            lines.append(f'| {mode} | {label} | ' + ' | '.join(cells) + ' |')
    links = links or {}
    defined = [(f'- [`{v}`]({links[v]})' if v in links else f'- `{v}`')
               + f'{" (this table)" if v == variant else ""}: {VARIANTS.get(v, "config/reward.yaml")}'
               for v in dict.fromkeys(r['variant'] for r in rows)]
    return '\n'.join(lines + ['', f'{len(seeds)} test seeds, reward variant `{variant}`; ↑ / ↓: the interval '
                                  f'excludes 0. The reward variants:', *defined, ''])


def _by_side(sides: Mapping[str, int], words: Mapping[int, str] = _SIDES) -> str:
    """{mode: side} as 'above under CONP; not resolved under AGGI, AGGP'."""
    return '; '.join(f'{words[side]} under {", ".join(m for m, s in sides.items() if s == side)}'
                     for side in (1, -1, 0) if side in sides.values())


def readme_verdict(rows: list[dict], modes: list[str], variant: str, policy: str, neutral: str) -> str:
    """The README's verdict on the policy labelled ``policy``, from the rows of its table: what its
    return beats and where it is not resolved, its CAV collisions beside the best fixed driver's
    ("safely" only while it has no more under any mode), and what it costs the traffic."""
    by, seeds = _by_run_and_seed(rows, variant, neutral)
    if (f'{policy}{AT}{modes[0]}', seeds[0]) not in by:
        return 'No policy in the results table: it holds the drivers a learned policy must beat.'
    best = best_fixed_drivers(by, seeds, modes)
    run = {mode: f'{policy}{AT}{mode}' for mode in modes}

    def sides(other: Callable[[str], str], key: Callable[[str], str]) -> dict[str, int]:
        return {mode: _side(*_interval(by, run[mode], other(mode), seeds, key(mode))[1:]) for mode in modes}

    returns = ' '.join(f'Against {name}: ' + _by_side(sides(other, lambda mode: f'return_{mode}')) + '.'
                       for name, other in (('the best fixed driver', best.get), ('the neutral driver', lambda _: neutral),
                                           ("SUMO's drivers", lambda _: 'sumo')))
    collisions = {mode: (_mean(by, run[mode], seeds, 'p_collision_CAV'), _mean(by, best[mode], seeds, 'p_collision_CAV'))
                  for mode in modes}
    more = [mode for mode, (own, fixed_) in collisions.items() if own > fixed_]
    safety = (f'**Not safer than a fixed driver yet:** more CAV collisions than the best fixed driver under '
              f'{", ".join(more)}' if more else
              '**It takes its CAVs to the exit safely on these seeds:** no more CAV collisions than the best fixed '
              'driver under any mode')
    cost = '; '.join(f'{mode} {_interval_text(by, run[mode], best[mode], seeds, "N_braking", 2)}' for mode in modes)
    return '\n'.join([
        f'**The shipped policy**, `{policy}` (what `scripts/main`, `exit-decision stack` and `ros2 launch` run), on '
        f'{len(seeds)} test seeds, reward variant `{variant}` ([the table](#results)):',
        f'- **Its return** (paired 95% intervals). {returns}',
        f'- {safety} (the share of CAVs in a collision, the policy against the best fixed driver: '
        + ', '.join(f'{mode} {own:.4f} against {fixed_:.4f}' for mode, (own, fixed_) in collisions.items()) + ').',
        '- **What it costs the traffic:** hard brakings per episode of all vehicles, against the best fixed driver: '
        + _by_side(sides(best.get, lambda _: 'N_braking'), {1: 'more', -1: 'fewer', 0: 'not resolved'})
        + f' ({cost}).'])


def write_table(config: ProjectConfig, seeds: list[int], variants: list[str], jobs: int, out_dir: Path,
                command: str, policies: dict[str, Path] | None = None) -> str:
    """Runs the table and writes ``constant_options.csv`` (per episode and reward variant) and
    ``.md`` into ``out_dir``; with ``policies`` (label -> checkpoint), their runs at each mode
    against the best fixed driver of that mode and SUMO's drivers, paired on the same seeds."""
    rows = run_table(config, seeds, variants, jobs, policies)
    write_rows(out_dir / 'constant_options.csv', rows)
    text = (f'# Constant options and the references, scored under every mode\n\nMade by `{command}` (seeds '
            f'{seeds[0]}..{seeds[-1]}); per-episode rows in '
            f'`constant_options.csv`. `option_<style>`: every CAV drives the route\'s lane plan in that style of '
            f'config/env.yaml `options` with the options\' low level; `grid_rule_based`: the neutral '
            f'rule-based driver on the 81-action grid; `sumo`: SUMO\'s own drivers. Columns: means over the '
            f'episodes; per mode the mean return and, in brackets, the paired difference to `option_neutral` '
            f'with its 95% interval (↑ / ↓: the interval excludes 0).\n\n'
            + '\n\n'.join(table_markdown(rows, config.mode_matrix.modes, variant, neutral_run(config),
                                           orderings=config.mode_matrix.aggressive_orderings) for variant in variants) + '\n')
    (out_dir / 'constant_options.md').write_text(text, encoding='utf-8')
    return text
