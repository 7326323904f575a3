"""The ``evaluate`` command: runs on fixed test seeds, tables in CSV and Markdown."""
from __future__ import annotations

import csv
import json
import re
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from exit_decision.actions import ActionGrid
from exit_decision.config import ProjectConfig, RuleBasedConfig
from exit_decision.env import ExitDecisionEnv
from exit_decision.errors import UsageError
from exit_decision.driving import fixed
from exit_decision.evaluation.evaluate import EvaluatedRun, EvaluationResult, evaluate_policy, play_episodes, scored_episodes
from exit_decision.evaluation.metrics import markdown_table, summarize
from exit_decision.evaluation.statistics import paired_difference, paired_interval
from exit_decision.model.names import (DEFAULT_ALGORITHM, GRID_ALGORITHM, ROLES, described, is_conditioned, method_of,
                                       run_name)
from exit_decision.tables import read_rows, write_rows
from exit_decision.visualization.episodes import ShowEpisodes


TEACHER = 'rule_based'   # the neutral rule-based driver
SUMO = 'sumo'           # SUMO's own IDM + LC2013 drivers, routed to the exit
REFERENCE_DRIVERS = (SUMO, TEACHER)
#: columns of the paired comparison with the teacher (difference run - teacher per seed)
PAIRED_METRICS = ('reward', 'v_AVs', 'p_CAV', 'p_collision_CAV', 'N_braking')


def evaluate_runs(config: ProjectConfig, policies: Sequence[Path], drivers: Sequence[str], modes: Sequence[str],
                  episodes: int, seed: int, out_dir: Path, command: str,
                  sanity_drivers: dict[str, RuleBasedConfig] | None = None, show: ShowEpisodes | None = None) -> str:
    """Evaluate each policy and reference driver on seeds seed..seed+episodes-1, scored under
    each named mode's reward.

    Drivers: ``sumo``, ``rule_based`` (the neutral teacher) or ``rule_based:<name>`` (a driver of
    the reward sanity sweep, ``sanity_drivers``). A driver or per-mode policy drives once and is scored under every mode; a conditioned
    policy drives at each mode's weights. Writes ``<run>_<mode>.csv`` (per episode; ``reward``
    = the episode's global scalar return under that mode, unscaled), ``<run>_<mode>_actions.csv``,
    ``summary.md`` / ``summary.csv`` (mean and std), and ``comparison.md`` / ``comparison.csv``
    (every run against the neutral teacher under the same mode, paired over seeds). ``show``:
    draw the first episodes of each run (time-space diagram, bird's-eye clip)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = list(range(seed, seed + episodes))
    for mode in modes:
        config.mode(mode)
    runs: list[EvaluatedRun] = []
    for driver in drivers:
        runs += driver_runs(config, driver, modes, seeds, sanity_drivers, show)
    env = ExitDecisionEnv(config, mode=modes[0])
    try:
        for path in policies:
            runs += evaluate_policy(env, path, modes, seeds, show)
    finally:
        env.close()
    summaries = [(run.label, write_run(out_dir, run, ActionGrid(config.env.actions))) for run in runs]
    table = markdown_table(summaries)
    with open(out_dir / 'summary.csv', 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['run', 'metric', 'mean', 'std'])
        for label, summary in summaries:
            for metric, (mean, std) in summary.items():
                writer.writerow([label, metric, mean, std])
    (out_dir / 'config.json').write_text(json.dumps(config.model_dump(), indent=2), encoding='utf-8')
    header = (f'# Evaluation on seeds {seeds[0]}..{seeds[-1]} ({episodes} episodes)\n\nMade by `{command}` '
              f'(configuration: `config.json`; learned policies with the lane planner '
              f'{"on" if config.env.lane_planner else "off"})')
    (out_dir / 'summary.md').write_text(f'{header}; mean ± std over episodes.\n\n{table}\n', encoding='utf-8')
    comparison = paired_comparison(runs, modes, config.scenario.max_steps)
    if comparison:
        write_rows(out_dir / 'comparison.csv', comparison)
        (out_dir / 'comparison.md').write_text(
            f'{header}.\n\n{comparison_markdown(comparison)}\n', encoding='utf-8')
    return table


def driver_runs(config: ProjectConfig, driver: str, modes: Sequence[str], seeds: Sequence[int],
                sanity_drivers: dict[str, RuleBasedConfig] | None = None,
                show: ShowEpisodes | None = None) -> list[EvaluatedRun]:
    """A reference driver (``sumo``, ``rule_based`` or ``rule_based:<name>``) on the seeds, in
    its own environment: played once, scored under each mode."""
    name, _, variant = driver.partition(':')   # rule_based:<driver of the sanity sweep>
    parameters = sanity_drivers[variant] if variant else None
    env = ExitDecisionEnv(config, mode=modes[0], cav_driver='sumo' if name == SUMO else 'policy')
    try:
        result = EvaluationResult()
        played = play_episodes(env, fixed.sumo() if name == SUMO else fixed.rule_based(env, parameters), seeds,
                               result, desc=driver, show=show and show.named(driver.replace(':', '_')))
    finally:
        env.close()
    label = driver.replace(':', '_')
    return [EvaluatedRun(f'{label}_{mode}', scored_episodes(played, env.reward_fn.weights(config.mode(mode))), result)
            for mode in modes]


def write_run(out_dir: Path, run: EvaluatedRun, grid: ActionGrid) -> dict[str, tuple[float, float]]:
    """``<run>.csv`` (per episode) and, for a run that decided, ``<run>_actions.csv``; returns
    the run's summary (with the shield's override share)."""
    write_rows(out_dir / f'{run.label}.csv', run.episodes)
    summary = summarize(run.episodes)
    if run.result.decisions:
        write_action_counts(out_dir / f'{run.label}_actions.csv', run.result, grid)
        summary['shield_overrides'] = (run.result.overrides / run.result.decisions, 0.0)
    return summary


def write_action_counts(path: Path, result: EvaluationResult, grid) -> None:
    with open(path, 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['lane_change', 'acceleration', 'count', 'share'])
        total = result.action_counts.sum()
        for index in np.flatnonzero(result.action_counts):
            writer.writerow([grid.lane_change_of[index], grid.acceleration_of[index],
                             result.action_counts[index], result.action_counts[index] / total])


def paired_comparison(runs: Sequence[EvaluatedRun], modes: Sequence[str], max_steps: int) -> list[dict]:
    """Every run against the teacher under the same mode: per metric the run's mean (and
    95% interval where it is a rate), and the mean paired difference with its 95% interval."""
    by_label = {run.label: run for run in runs}
    rows = []
    for mode in modes:
        teacher = by_label.get(f'{TEACHER}_{mode}')
        if teacher is None:
            continue
        for run in runs:
            if not run.label.endswith(f'_{mode}') or run is teacher:
                continue
            row = {'run': run.label[:-len(mode) - 1], 'mode': mode, 'episodes': len(run.episodes),
                   'capped': sum(e['steps'] >= max_steps for e in run.episodes)}
            for metric in PAIRED_METRICS:
                own = np.array([e[metric] for e in run.episodes], dtype=float)
                mean, low, high = paired_interval(own)
                row.update({metric: mean, f'{metric}_low': low, f'{metric}_high': high})
                mean, low, high = paired_difference(run.episodes, teacher.episodes, metric)
                row.update({f'd_{metric}': mean, f'd_{metric}_low': low, f'd_{metric}_high': high})
            rows.append(row)
    return rows


def comparison_markdown(rows: Sequence[dict]) -> str:
    """Each run minus the teacher (rule_based) under the same mode: mean [95% interval]."""
    def cell(row: dict, key: str, digits: int = 3) -> str:
        mark = ' ↑' if row[f'{key}_low'] > 0 else ' ↓' if row[f'{key}_high'] < 0 else ''
        return f'{row[key]:+.{digits}f} [{row[f"{key}_low"]:+.{digits}f}, {row[f"{key}_high"]:+.{digits}f}]{mark}'
    lines = ['| run | mode | return − teacher | v_AVs − teacher | p_CAV [95%] | p_collision_CAV [95%] | '
             'N_braking − teacher |', '|---|---|---|---|---|---|---|']
    for row in rows:
        lines.append(f'| {row["run"]} | {row["mode"]} | {cell(row, "d_reward")} | {cell(row, "d_v_AVs")} | '
                     f'{row["p_CAV"]:.3f} [{row["p_CAV_low"]:.3f}, {row["p_CAV_high"]:.3f}] | '
                     f'{row["p_collision_CAV"]:.4f} [{row["p_collision_CAV_low"]:.4f}, {row["p_collision_CAV_high"]:.4f}] | '
                     f'{cell(row, "d_N_braking", 2)} |')
    return '\n'.join(lines)


def read_summary(path: Path) -> dict[str, dict[str, tuple[float, float]]]:
    """summary.csv -> {run: {metric: (mean, std)}}."""
    runs: dict[str, dict[str, tuple[float, float]]] = {}
    for row in read_rows(path):
        runs.setdefault(row['run'], {})[row['metric']] = (float(row['mean']), float(row['std']))
    return runs


def interval_text(row: dict, key: str, digits: int = 3) -> str:
    mean, low, high = (float(row[k]) for k in (key, key + '_low', key + '_high'))
    return f'{mean:+.{digits}f} [{low:+.{digits}f}, {high:+.{digits}f}]'


def target_checks(comparison: Sequence[dict], conditioned: str = GRID_ALGORITHM,
                  exit_target: float = 0.99, collision_target: float = 0.0067) -> list[str]:
    """The targets of the learning issue, checked on comparison.csv (every run against the
    neutral teacher under the same mode, paired over the test seeds)."""
    rows = {(r['run'], r['mode']): r for r in comparison}
    modes = [m for run, m in rows if run == conditioned]
    lines = []
    for mode in modes:
        r = rows[(conditioned, mode)]
        safe = float(r['p_CAV']) >= exit_target and float(r['p_collision_CAV']) <= collision_target and not float(r['capped'])
        beats = float(r['d_reward_low']) > 0
        lines.append(f'- {mode}: Exit-1 {float(r["p_CAV"]):.3f} (>= {exit_target}), CAV collisions '
                     f'{float(r["p_collision_CAV"]):.4f} (<= {collision_target}), {int(float(r["capped"]))} capped: '
                     f'{"met" if safe else "NOT met"}; return − teacher {interval_text(r, "d_reward")}: '
                     f'{"beats the teacher" if beats else "does NOT beat the teacher"}')
        best = [(run, x) for (run, m), x in rows.items() if m == mode and run.startswith('rule_based_')]
        if best:
            run, x = max(best, key=lambda item: float(item[1]['reward']))
            diff = float(r['reward']) - float(x['reward'])
            lines.append(f'  - against the best sanity-sweep driver under {mode} on these seeds ({run}): '
                         f'return {float(r["reward"]):.3f} vs {float(x["reward"]):.3f} ({diff:+.3f}, means)')
        for (run, m), x in rows.items():
            if m == mode and run == run_name(method_of(conditioned), mode):
                gap = float(r['reward']) - float(x['reward'])
                lines.append(f'  - against the per-mode network {run}: return {float(r["reward"]):.3f} vs '
                             f'{float(x["reward"]):.3f} ({gap:+.3f}, {gap / abs(float(x["reward"])):+.1%} of its '
                             f'magnitude; target: not below by more than 2%)')
    return lines


def speed_orderings(evaluation_dir: Path, run: str, pairs: Sequence[tuple[str, str]]) -> list[str]:
    """Paired speed differences between modes of one run on the same seeds, for each (faster,
    slower) pair (``ModeMatrix.speed_orderings``: what the modes' names promise)."""
    lines = []
    for fast, slow in pairs:
        a, b = evaluation_dir / f'{run}_{fast}.csv', evaluation_dir / f'{run}_{slow}.csv'
        if not (a.exists() and b.exists()):
            continue
        mean, low, high = paired_difference(read_rows(a), read_rows(b), 'v_AVs')
        verdict = 'holds' if low > 0 else 'reversed' if high < 0 else 'not resolved'
        lines.append(f'- {run}: {fast} faster than {slow}: v_AVs {mean:+.3f} m/s [{low:+.3f}, {high:+.3f}]: {verdict}')
    return lines


def recipe(run_dir: Path) -> str | None:
    """A training run's recipe as its config.json gives it (demonstrations, pre-training, RL
    episodes, seed, reward variant); None without one."""
    path = run_dir / 'config.json'
    if not path.exists():
        return None
    run = json.loads(path.read_text())
    demonstrations = run['config']['training']['demonstrations']
    taught = (f'{demonstrations["episodes"]} demonstration episodes, {demonstrations["pretrain_updates"]} pre-training '
              'updates' if demonstrations['episodes'] else 'no demonstrations, no pre-training')
    return (f'{taught}, {run["episodes"]} RL episodes, seed {run["seed"]}, reward variant '
            f'`{run["config"]["env"]["reward_variant"]}`')


def training_lines(run_dirs: Sequence[Path]) -> list[str]:
    """Per training run: its recipe, the checkpoint kept, its validation and the run's wall time."""
    lines = []
    for run_dir in run_dirs:
        validation = run_dir / 'validation.csv'
        if not validation.exists():
            continue
        rows = read_rows(validation)
        best = max(rows, key=lambda r: float(r['score']))
        kept = [r for r in rows if r['episode'] == best['episode']]
        timing = run_dir / 'timing.json'
        wall = json.loads(timing.read_text()) if timing.exists() else {}
        made = recipe(run_dir) or f'{max(int(r["episode"]) for r in rows)} RL episodes after pre-training'
        lines.append(f'- {described(run_dir.name)}: {made}'
                     + (f'; {wall["total_s"] / 60:.0f} min wall time ({wall.get("note", "")})' if wall else '')
                     + f'; kept the checkpoint of episode {best["episode"]} (score {float(best["score"]):.3f}): '
                     + ', '.join(f'{r["mode"]} gain {float(r["gain"]):+.3f}, Exit-1 {float(r["p_CAV"]):.3f}' for r in kept))
    return lines


def step_cap_lines(evaluation_dir: Path, max_steps: int) -> list[str]:
    """Per run, the test episodes that ran into the step cap: a CAV stopped on the road held
    the traffic up until the episode was cut (its exit rate alone does not show this)."""
    lines = []
    for path in sorted(evaluation_dir.glob('*.csv')):
        if path.stem in ('summary', 'comparison') or path.stem.endswith('_actions'):
            continue
        rows = read_rows(path)
        capped = sum(float(row['steps']) >= max_steps for row in rows)
        if capped:
            lines.append(f'- {path.stem}: {capped} of {len(rows)} episodes ran into the {max_steps}-step cap')
    return lines or [f'- none: no episode ran into the {max_steps}-step cap']


def _body(page: Path) -> str:
    """A generated page without its title line and the blank line after it."""
    return page.read_text().split('\n', 2)[2].strip()


def benchmark_lines(benchmarks: Path, relative: Callable[[Path], str]) -> list[str]:
    """The results page's speed section: a link to the benchmarks' logs (``benchmarks``, the
    output of ``exit-decision bench``, kept whole there), not a copy of them; none without them."""
    if not benchmarks.is_file():
        return []
    performance = benchmarks.parent.parent / 'performance.md'
    return ['## Speed of the software', '',
            f'The logs of `exit-decision bench` (each block after its `$` command): '
            f'[`{relative(benchmarks)}`]({relative(benchmarks)})'
            + (f'; what each figure means, the targets and the latest figures: [`{performance.name}`]'
               f'({relative(performance)})' if performance.is_file() else '') + '.', '']


def figure_lines(figures_dir: Path, relative: Callable[[Path], str]) -> list[str]:
    """The results page's figures, folder by folder (``figures_dir`` and the folders in it), each
    under the policies whose training run drew it (its ``validation_<run>.png``)."""
    folders = [folder for folder in (figures_dir, *sorted(p for p in figures_dir.glob('*') if p.is_dir()))
               if any(folder.glob('*.png'))]
    lines = ['## Figures', '', 'Drawn by `exit-decision plot`; what each shows and the command that draws it: '
             '[figures.md](figures.md).', ''] if folders else []
    for folder in folders:
        runs = [path.stem.removeprefix('validation_') for path in sorted(folder.glob('validation_*.png'))]
        made = ', '.join(f'`{run}`' + (f' ({ROLES[run]})' if run in ROLES else '') for run in runs) or 'no training run'
        lines += [f'### `{relative(folder)}/`: {made}', '',
                  *[f'![{path.stem}]({relative(path)})' for path in sorted(folder.glob('*.png'))], '']
    return lines


#: the results page's section of the options table of the test seeds (the README's table)
OPTIONS_HEADING = '## Over options: the learned policies against the fixed drivers (test seeds)'
VARIANT_HEADING = re.compile(r'^### Reward variant `([^`]+)`')


def anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading's text (before a repeat's ``-1``, ``-2``)."""
    return '-'.join(''.join(c for c in heading.lower() if c.isalnum() or c in ' -_').split(' '))


def variant_links(page: Path, url: str) -> dict[str, str]:
    """Per reward variant, the link (``url`` + anchor) to its table in the results page's section
    ``OPTIONS_HEADING``; GitHub numbers a repeated heading's anchor."""
    seen, links, section, fenced = Counter(), {}, '', False
    for line in page.read_text(encoding='utf-8').splitlines():
        fenced ^= line.startswith('```')
        if fenced or not line.startswith('#'):
            continue
        slug = anchor(line.lstrip('#').strip())
        repeat, seen[slug] = seen[slug], seen[slug] + 1
        section = line if line.startswith('## ') else section
        variant = VARIANT_HEADING.match(line)
        if variant and section == OPTIONS_HEADING:
            links.setdefault(variant[1], f'{url}#{slug}' + (f'-{repeat}' if repeat else ''))
    return links


def results_page(evaluation_dir: Path, run_dirs: Sequence[Path], sanity_dir: Path, tradeoff_dir: Path,
                 figures_dir: Path, out: Path, max_steps: int, speed_pairs: Sequence[tuple[str, str]],
                 options_dir: Path | None = None) -> Path:
    """docs/results.md from the generated artefacts: nothing in it is typed by hand. ``options_dir``:
    an ``options-table`` of the test seeds (the policies over options against the fixed drivers)."""
    relative = lambda path: Path(path).resolve().relative_to(out.parent.resolve()).as_posix()  # noqa: E731
    commands = evaluation_dir.parent / 'commands.txt'
    comparison = read_rows(evaluation_dir / 'comparison.csv')
    parts = ['# Results', '',
             'Generated by `exit-decision report` from the outputs of the commands below; rerun them to '
             'reproduce every number. Intervals are 95% (normal approximation) over paired seeds.', '',
             *(['```', commands.read_text().strip(), '```', ''] if commands.exists() else []),
             '## The reward prefers what its mode names (before any training)', '']
    tables = [('', sanity_dir / 'reward_sanity.md')]
    if options_dir is not None:   # and the safety row's ablation beside it, when made (docs/results/commands.txt)
        tables += [(OPTIONS_HEADING,
                    options_dir / 'constant_options.md'),
                   (f'## Ablation: the safety row (the shipped policy, `{DEFAULT_ALGORITHM}`, beside one trained with '
                    'the previous row)',
                    options_dir.parent / 'ablation' / 'constant_options.md')]
    for heading, page in tables:
        if page.exists():
            parts += [*([heading, ''] if heading else []), _body(page), '']
    parts += ['## On the grid: the learned policies against their teacher (test seeds never used in training)', '',
              _body(evaluation_dir / 'comparison.md'), '',
              'Each row: the run minus the neutral rule-based teacher (`rule_based`) on the same seeds, under the '
              'named mode\'s reward (the paper\'s global scalar reward, unscaled); ↑ / ↓: the interval excludes 0. '
              f'Per-episode rows: [`{relative(evaluation_dir)}/`]({relative(evaluation_dir)}/).', '',
              '## Targets', '', *target_checks(comparison), '',
              '## Speed orderings between modes (paired over the test seeds)', '',
              'A conditioned policy acts at each mode\'s weights; drivers and per-mode policies drive the same '
              'episodes whatever the mode scoring them, so only the conditioned runs are compared here.', '',
              *[line for run in sorted({r['run'] for r in comparison if is_conditioned(r['run'])})
                for line in speed_orderings(evaluation_dir, run, speed_pairs)], '',
              '## Episodes cut by the step cap', '', *step_cap_lines(evaluation_dir, max_steps), '',
              '## Training', '', *training_lines(run_dirs), '']
    tradeoff = tradeoff_dir / 'tradeoff.png'
    if tradeoff.exists():
        parts += ['## Trade-off from one checkpoint', '', f'![tradeoff]({relative(tradeoff)})', '',
                  f'Values: [`{relative(tradeoff_dir)}/tradeoff.csv`]({relative(tradeoff_dir)}/tradeoff.csv).', '']
    parts += benchmark_lines(evaluation_dir.parent / 'benchmarks.txt', relative)
    parts += figure_lines(figures_dir, relative)
    out.write_text('\n'.join(parts) + '\n', encoding='utf-8')
    return out


#: the README lines between which ``report`` writes the results table
README_MARKERS = ('<!-- results table: written by `exit-decision report` -->', '<!-- end of results table -->')
#: the README's generated blocks (name -> its first and last line): ``report`` writes what stands between
README_BLOCKS = {'verdict': ('<!-- verdict: written by `exit-decision report` -->', '<!-- end of verdict -->'),
                 'table': README_MARKERS}


def write_readme_block(readme: Path, block: str, text: str) -> Path:
    """Replaces what stands between the markers of ``README_BLOCKS[block]`` with ``text``; refuses
    a README without the markers."""
    content = readme.read_text(encoding='utf-8')
    begin, end = README_BLOCKS[block]
    if content.count(begin) != 1 or content.count(end) != 1 or content.index(begin) > content.index(end):
        raise UsageError(f'{readme}: needs the lines {begin!r} and then {end!r}, once each')
    head, rest = content.split(begin)
    _, tail = rest.split(end)
    readme.write_text(f'{head}{begin}\n{text}\n{end}{tail}', encoding='utf-8')
    return readme


def write_readme_table(readme: Path, table: str, command: str) -> Path:
    """The README's results table block: ``table`` and the command that made its rows."""
    return write_readme_block(readme, 'table', f'{table}\nRows made by `{command}`.')
