"""The comparison's page (``docs/comparison.md``) and figures, read back from a compare sweep.

A learned method trained with several seeds is one row: its episodes on each test seed are
averaged over the training seeds first, so every interval is over test seeds (the same ones
for every method, which makes the differences paired). Per variant: the episode metrics
(``exit_decision.episode_log``; mean with 95% interval), each method against the neutral
teacher under every mode, then the papers' claims as paired differences under the training
mode, each said to hold, fail or stay unresolved by its interval; each method's drop from the
base scenario; the learning curves of all learned methods on one figure (the greedy validation
return, the return the tables give), against the RL decisions taken (the budget's unit), the
rows with our measures and the as-published ones in two panels (the teacher's validation return
as a line), and their training wall time per 100 episodes; every method's return on every
variant as its paired difference from the teacher's.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from exit_decision.config import PUBLISHED_SUFFIX
from exit_decision.evaluation.evaluate import EvaluatedRun, EvaluationResult
from exit_decision.evaluation.plots import plt, read_csv, rolling, save
from exit_decision.evaluation.report import SUMO, TEACHER, comparison_markdown, paired_comparison
from exit_decision.evaluation.statistics import paired_difference, paired_interval
from exit_decision.tables import read_rows

#: the episode metrics (``exit_decision.episode_log``), each with the direction that is better
#: (speeds: higher, as the efficiency term of every mode; collisions and braking: lower)
HIGHER_IS_BETTER = {'reward': True, 'p_CAV': True, 'p_HV2': True, 'p_collision_CAV': False, 'p_collision': False,
                    'v_AVs': True, 'v_s': True, 'N_braking': False, 'braking_steps': False}
TABLE_METRICS = tuple(HIGHER_IS_BETTER)
DRIVER_NOTES = {SUMO: ": SUMO's IDM + LC2013, paper 002's IDM + MOBIL"}
MIN_SEEDS_FOR_CLAIM = 3   # training seeds a learned method needs before a claim is made on it
#: the papers' claims: (statement, method, compared with); a missing method leaves the claim out
CLAIMS = (
    ('MDGQN > GQN (paper 000)', 'mdgqn', 'gqn'),
    ('DDQN > DQN (paper 002)', 'ddqn', 'dqn'),
    ('Dueling DQN > DQN (paper 002)', 'dueling_dqn', 'dqn'),
    ('Dueling DDQN + PER (6 nearest) > Dueling DQN (grid) (paper 003; PER, double target, state: together)',
     'dueling_ddqn_per', 'dueling_dqn'),
    ('PER helps: Dueling DDQN + PER > Dueling DDQN, both on the 6 nearest (paper 003)', 'dueling_ddqn_per',
     'dueling_ddqn'),
    ('SGRL > MGRL (paper 001)', 'sgrl', 'mgrl'),
    ('SGRL > NGRL (paper 001)', 'sgrl', 'ngrl'),
    ('MGRL (GCN) > NGRL (no GCN) (paper 001)', 'mgrl', 'ngrl'),
)


def episodes_of(path: Path) -> list[dict[str, float]]:
    return [{key: float(value) for key, value in row.items()} for row in read_rows(path)]


def averaged_over_training_seeds(runs: Sequence[list[dict[str, float]]]) -> list[dict[str, float]]:
    """One episode row per test seed: each metric's mean over the training seeds' runs."""
    by_seed: dict[float, list[dict[str, float]]] = {}
    for run in runs:
        for episode in run:
            by_seed.setdefault(episode['seed'], []).append(episode)
    return [{key: float(np.nanmean([e[key] for e in group])) for key in group[0]} for _, group in sorted(by_seed.items())]


def variant_runs(variant_dir: Path, learned: dict[str, list[str]], drivers: Sequence[str],
                 modes: Sequence[str]) -> dict[str, dict[str, list[dict[str, float]]]]:
    """method -> mode -> episode rows (learned methods averaged over their training runs)."""
    out: dict[str, dict[str, list[dict[str, float]]]] = {}
    for driver in drivers:
        found = {mode: episodes_of(variant_dir / f'{driver}_{mode}.csv') for mode in modes
                 if (variant_dir / f'{driver}_{mode}.csv').is_file()}
        if found:
            out[driver] = found
    for method, run_names in learned.items():
        found = {}
        for mode in modes:
            paths = [variant_dir / f'{name}_{mode}.csv' for name in run_names]
            if paths and all(path.is_file() for path in paths):
                found[mode] = averaged_over_training_seeds([episodes_of(path) for path in paths])
        if found:
            out[method] = found
    return out


def metrics_table(runs: dict[str, dict[str, list[dict[str, float]]]], mode: str) -> str:
    """Mean [95% interval] of every metric per method, and the return's standard deviation over test seeds."""
    header = ['method', *(f'{m} [95%]' for m in TABLE_METRICS), 'reward sd']
    lines = ['| ' + ' | '.join(header) + ' |', '|---' * len(header) + '|']
    for method, by_mode in runs.items():
        if mode not in by_mode:
            continue
        cells = []
        for metric in TABLE_METRICS:
            mean, low, high = paired_interval([e[metric] for e in by_mode[mode]])
            cells.append(f'{mean:.4g} [{low:.4g}, {high:.4g}]')
        cells.append(f'{np.std([e["reward"] for e in by_mode[mode]], ddof=1):.4g}')
        lines.append(f'| {method} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def winners_table(runs: dict[str, dict[str, list[dict[str, float]]]], mode: str) -> str:
    """Per metric, the method with the best mean and its paired difference from the runner-up:
    it wins when the interval excludes 0, else it ties with the runner-up."""
    lines = ['| metric (better) | best | mean | runner-up | best - runner-up [95%] | verdict |', '|---' * 6 + '|']
    evaluated = {method: by_mode[mode] for method, by_mode in runs.items() if mode in by_mode}
    if len(evaluated) < 2:
        return ''
    for metric, higher in HIGHER_IS_BETTER.items():
        sign = 1.0 if higher else -1.0
        means = {m: float(np.nanmean([e[metric] for e in evaluated[m]])) for m in evaluated}
        ranked = sorted((m for m in evaluated if np.isfinite(means[m])), key=lambda m: -sign * means[m])
        if len(ranked) < 2:
            continue
        best, second = ranked[:2]
        mean, low, high = paired_difference(evaluated[best], evaluated[second], metric)
        decided = low > 0 if higher else high < 0   # best - runner-up, away from 0 in the better direction
        lines.append(f'| {metric} ({"higher" if higher else "lower"}) | {best} | '
                     f'{means[best]:.4g} | {second} | '
                     f'{mean:+.4g} [{low:+.4g}, {high:+.4g}] | '
                     f'{"wins" if decided else "tied with the runner-up (interval includes 0)"} |')
    return '\n'.join(lines)


def verdict(low: float, high: float) -> str:
    return 'holds' if low > 0 else 'fails (reversed)' if high < 0 else 'unresolved (interval includes 0)'


def run_returns(variant_dir: Path, learned: dict[str, list[str]], mode: str) -> dict[str, list[float]]:
    """Per learned method, each training run's mean return on this variant under ``mode``."""
    out = {}
    for method, run_names in learned.items():
        paths = [variant_dir / f'{name}_{mode}.csv' for name in run_names]
        if paths and all(path.is_file() for path in paths):
            out[method] = [float(np.mean([e['reward'] for e in episodes_of(path)])) for path in paths]
    return out


def claim_lines(runs: dict[str, dict[str, list[dict[str, float]]]], mode: str, seeds: dict[str, int],
                per_run: dict[str, list[float]] | None = None) -> list[str]:
    """Each claim whose two sides were evaluated: the paired return difference and its verdict
    (a learned side with fewer than MIN_SEEDS_FOR_CLAIM training seeds: no verdict). The
    interval is over test seeds; ``per_run`` (each training run's mean return) adds how far
    the training seeds spread it: the difference of every pair of runs, min to max."""
    lines = []
    claims = [*CLAIMS,
              *((f'{method} with our measures > as published', method, method + PUBLISHED_SUFFIX)
                for method in runs if method + PUBLISHED_SUFFIX in runs),
              *((f'{method} > {driver} (learned > rule-based{DRIVER_NOTES.get(driver, "")})', method, driver)
                for driver in (TEACHER, SUMO) for method in runs if method not in (TEACHER, SUMO))]
    for statement, method, other in claims:
        if mode in runs.get(method, {}) and mode in runs.get(other, {}):
            mean, low, high = paired_difference(runs[method][mode], runs[other][mode], 'reward')
            few = [f'{m} has {seeds[m]} training seed(s)' for m in (method, other)
                   if seeds.get(m, MIN_SEEDS_FOR_CLAIM) < MIN_SEEDS_FOR_CLAIM]
            spread = ''
            if per_run and method in per_run:
                theirs = per_run.get(other, [float(np.mean([e['reward'] for e in runs[other][mode]]))])
                pairs = [a - b for a in per_run[method] for b in theirs]
                spread = (f'; training runs: {min(pairs):+.3f} to {max(pairs):+.3f}'
                          + (' (they disagree in sign)' if min(pairs) < 0 < max(pairs) else ''))
            lines.append(f'- {statement}: return difference {mean:+.3f} [{low:+.3f}, {high:+.3f}]{spread}: '
                         + (f'no verdict ({"; ".join(few)})' if few else f'**{verdict(low, high)}**'))
    return lines


def drop_table(per_variant: dict[str, dict[str, dict[str, list[dict[str, float]]]]], base: str, mode: str) -> str:
    """Each method's Exit-1 rate and return on every variant minus on the base scenario, paired
    by test seed, with its 95% interval; a change whose interval excludes 0 is marked *."""
    variants = [v for v in per_variant if v != base]
    lines = ['| method | ' + ' | '.join(f'{v}: Δp_CAV / Δreturn [95%]' for v in variants) + ' |',
             '|---' * (len(variants) + 1) + '|']

    def change(episodes, base_episodes, metric: str) -> str:
        mean, low, high = paired_difference(episodes, base_episodes, metric)
        return f'{mean:+.3g} [{low:+.3g}, {high:+.3g}]' + ('*' if low > 0 or high < 0 else '')
    for method, by_mode in per_variant.get(base, {}).items():
        if mode not in by_mode:
            continue
        cells = []
        for variant in variants:
            episodes = per_variant[variant].get(method, {}).get(mode)
            cells.append('—' if not episodes else
                         f'{change(episodes, by_mode[mode], "p_CAV")} / {change(episodes, by_mode[mode], "reward")}')
        lines.append(f'| {method} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def is_published(method: str) -> bool:
    """A baseline's as-published row: its returns are far below every other row's, so the
    figures give those rows a panel of their own."""
    return method.endswith(PUBLISHED_SUFFIX)


def stacked_panels(count: int, width: float, sharex: bool = False):
    """A figure of ``count`` panels, 4 inches high each, one above the other (an array of axes)."""
    fig, axes = plt.subplots(count, 1, figsize=(width, 4 * count), sharex=sharex, squeeze=False)
    return fig, axes[:, 0]


CURVE_GRID = 200   # points of the common grid of decisions a method's seeds are averaged on
DODGE = 0.006      # sideways shift of each method's points, a share of the decisions axis, so bars do not hide


def validation_points(run_dir: Path, mode: str | None) -> tuple[np.ndarray, np.ndarray, float] | None:
    """One run's validated candidates: the RL decisions taken at each (0: the pre-trained
    network), its greedy return on the validation seeds under ``mode`` (default: the first mode
    validated) and the teacher's return there; None without a validation log."""
    path, training = run_dir / 'validation.csv', run_dir / 'training.csv'
    rows = read_rows(path) if path.is_file() else []
    if not rows or 'return' not in rows[0]:
        return None
    mode = mode if any(row['mode'] == mode for row in rows) else rows[0]['mode']
    by_episode = {int(row['episode']): row for row in rows if row['mode'] == mode}   # a re-validation: the last
    curve = read_csv(training) if training.is_file() else {}
    after = dict(zip(curve.get('episode', ()), curve.get('decisions', ())))   # decisions after each episode
    episodes = [e for e in sorted(by_episode) if e == 0 or e - 1 in after]
    if not episodes:
        return None
    return (np.array([after[e - 1] if e else 0.0 for e in episodes]),
            np.array([float(by_episode[e]['return']) for e in episodes]),
            float(np.mean([float(row['teacher_return']) for row in by_episode.values()])))


def training_curve(training_dir: Path, run_names: list[str]) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The exploring training episodes' return (for runs without a validation log): mean over the
    seeds on a common grid of decisions, rolling mean over a tenth of it (at each window's end)."""
    curves = [read_csv(training_dir / name / 'training.csv') for name in run_names
              if (training_dir / name / 'training.csv').is_file()]
    curves = [increasing_decisions(c) for c in curves if len(c.get('reward', ())) > 1]
    if not curves:
        return None
    grid = np.linspace(max(c['decisions'][0] for c in curves), min(c['decisions'][-1] for c in curves), CURVE_GRID)
    smoothed = rolling(np.mean([np.interp(grid, c['decisions'], c['reward']) for c in curves], axis=0),
                       CURVE_GRID // 10)
    return grid[len(grid) - len(smoothed):], smoothed, len(curves)


def learning_curves(training_dir: Path, learned: dict[str, list[str]], out: Path,
                    mode: str | None = None) -> Path | None:
    """Every learned method's greedy validation return under ``mode`` (the training mode: the
    return the tables give, there on the test seeds) at each validated candidate, against the RL
    decisions taken by then (the unit of the budget; methods' episodes differ in length): at the
    k-th candidate of every seed, the mean over the seeds with their min to max as a bar; a
    method whose runs logged no validation shows its exploring training return instead (said in
    its label). The rows with our measures and the as-published ones in a panel each (their
    returns are far apart), a method and its published row in one colour; the teacher's
    validation return as a line."""
    colours = plt.get_cmap('tab10').colors
    bases = list(dict.fromkeys(method.removesuffix(PUBLISHED_SUFFIX) for method in learned))
    panels: dict[bool, list[tuple[str, int, np.ndarray, np.ndarray, np.ndarray | None]]] = {}
    teacher = []
    for method, run_names in learned.items():
        base = bases.index(method.removesuffix(PUBLISHED_SUFFIX))
        validated = [validation_points(training_dir / name, mode) for name in run_names]
        validated = [points for points in validated if points is not None]
        if validated and len(validated) == len([n for n in run_names if (training_dir / n).is_dir()]):
            count = min(len(x) for x, _, _ in validated)
            x = np.mean([x[:count] for x, _, _ in validated], axis=0)
            returns = np.array([y[:count] for _, y, _ in validated])
            spread = np.array([returns.mean(axis=0) - returns.min(axis=0), returns.max(axis=0) - returns.mean(axis=0)])
            panels.setdefault(is_published(method), []).append(
                (f'{method} ({len(validated)} seeds)', base, x, returns.mean(axis=0), spread))
            teacher += [t for _, _, t in validated]
            continue
        curve = training_curve(training_dir, run_names)
        if curve is not None:
            x, y, seeds = curve
            panels.setdefault(is_published(method), []).append(
                (f'{method} ({seeds} seeds; exploring training return, no validation log)', base, x, y, None))
    if not panels:
        return None
    fig, axes = stacked_panels(len(panels), 10, sharex=True)
    right = max(float(x[-1]) for rows in panels.values() for _, _, x, _, _ in rows)
    for ax, published in zip(axes, sorted(panels)):
        rows = panels[published]
        for i, (label, base, x, y, spread) in enumerate(rows):
            style = dict(color=colours[base % len(colours)], linestyle=('-', '--', ':')[base // len(colours) % 3],
                         label=label)
            if spread is None:
                ax.plot(x, y, **style)
            else:
                ax.errorbar(x + (i - (len(rows) - 1) / 2) * DODGE * right, y, yerr=spread, marker='o', ms=4,
                            capsize=2, lw=1.2, **style)
        if teacher:
            ax.axhline(float(np.mean(teacher)), color='black', linestyle=':', label='teacher (validation seeds)')
        ax.set_title('as published (learning from its paper\'s reward)' if published else 'with our measures',
                     fontsize=9)
        ax.set_ylabel(f'validation return{f" under {mode}" if mode else ""}\n(greedy, as in the tables)')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc='center left', bbox_to_anchor=(1.01, 0.5))
    axes[-1].set_xlabel('RL decisions taken (0 = the pre-trained network)')
    fig.suptitle('Greedy return on the validation seeds at each validated candidate: mean over the training seeds, '
                 'bars min to max\n(the tables: each run\'s best-scoring candidate on the test seeds)', fontsize=9)
    return save(fig, out)


def increasing_decisions(curve: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A training log's rows whose decision count exceeds every row's before it (a run resumed
    from its last checkpoint logs the episodes after it again, counting from there)."""
    decisions = curve['decisions']
    kept = decisions > np.concatenate([[-np.inf], np.maximum.accumulate(decisions)[:-1]])
    return {name: values[kept] for name, values in curve.items()}


def variant_figure(per_variant: dict[str, dict[str, dict[str, list[dict[str, float]]]]], mode: str,
                   out: Path, reference: str = TEACHER) -> Path | None:
    """Per method across the variants, its return under the training mode minus the reference
    driver's (the neutral teacher) on the same test seeds, mean with its 95% interval, the axis
    on the differences and the teacher the line at 0 (its return per variant under the tick);
    without the reference on every variant, the returns themselves. The reference drivers and
    the rows with our measures in one panel, the as-published rows (two orders of magnitude
    below) in another; 10 colours, 20 for more methods."""
    variants = list(per_variant)
    paired = all(mode in per_variant[v].get(reference, {}) for v in variants)
    methods = sorted({m for runs in per_variant.values() for m in runs if not (paired and m == reference)})
    groups = [group for group in ([m for m in methods if not is_published(m)], [m for m in methods if is_published(m)])
              if group]
    if not groups:
        return None
    fig, axes = stacked_panels(len(groups), 11)
    ticks = [f'{v}\n({reference} {np.mean([e["reward"] for e in per_variant[v][reference][mode]]):.2f})'
             if paired else v for v in variants]
    for ax, group in zip(axes, groups):
        width = 0.8 / len(group)
        colours = plt.get_cmap('tab10' if len(group) <= 10 else 'tab20').colors
        for i, method in enumerate(group):
            xs, means, errors = [], [], []
            for j, variant in enumerate(variants):
                episodes = per_variant[variant].get(method, {}).get(mode)
                if episodes:
                    mean, low, high = (paired_difference(episodes, per_variant[variant][reference][mode], 'reward')
                                       if paired else paired_interval([e['reward'] for e in episodes]))
                    xs.append(j + (i - len(group) / 2 + 0.5) * width)
                    means.append(mean)
                    errors.append([mean - low, high - mean] if np.isfinite(low) else [0.0, 0.0])
            ax.errorbar(xs, means, yerr=np.array(errors).T.reshape(2, -1), fmt='o', ms=4, capsize=2, label=method,
                        color=colours[i % len(colours)])
        for j in range(1, len(variants)):
            ax.axvline(j - 0.5, color='grey', lw=0.5, alpha=0.5)
        if paired:
            ax.axhline(0.0, color='black', lw=1.0, label=f'{reference} (the teacher)')
        ax.set_xlim(-0.5, len(variants) - 0.5)
        ax.set_xticks(range(len(variants)), ticks, fontsize=8)
        ax.set_ylabel((f'return under {mode} − {reference}\n(paired by test seed, 95% interval)' if paired else
                       f'episode return under {mode}\n(95% interval)'))
        ax.grid(alpha=0.3, axis='y')
        ax.legend(fontsize=7, loc='center left', bbox_to_anchor=(1.01, 0.5))
    return save(fig, out)


def wall_time_lines(training_dir: Path, learned: dict[str, list[str]]) -> list[str]:
    """Per method: training wall time and the environment it used (RL episodes, simulation
    steps and decisions of the RL phase), means over its seeds."""
    header = ('| method | training wall time per 100 RL episodes, validation included [s] | total per run [s] | '
              'RL episodes | simulation steps | decisions |')
    lines = [header, '|---' * 6 + '|']
    for method, run_names in learned.items():
        timings = [json.loads((training_dir / name / 'timing.json').read_text()) for name in run_names
                   if (training_dir / name / 'timing.json').is_file()]
        curves = [read_csv(training_dir / name / 'training.csv') for name in run_names
                  if (training_dir / name / 'training.csv').is_file()]
        curves = [curve for curve in curves if curve]
        if timings and curves:
            per_100 = np.mean([100.0 * t['rl_s'] / t['episodes'] for t in timings])
            steps = np.mean([np.sum(c['steps']) for c in curves])
            decisions = np.mean([c['decisions'][-1] for c in curves])
            lines.append(f'| {method} | {per_100:.0f} | {np.mean([t["total_s"] for t in timings]):.0f} | '
                         f'{np.mean([len(c["steps"]) for c in curves]):.0f} | {steps:.0f} | {decisions:.0f} |')
    return lines


def budget_words(budget: dict | None) -> str:
    """What every learned method got alike, in words: environment steps, or RL episodes."""
    steps = (budget or {}).get('environment_steps')
    if steps:
        return (f'environment steps ({steps} RL decisions a run, ending with the episode that reaches them; '
                f'`episodes` below is only a cap, and a decay given in steps, `*_steps`, replaces the one in '
                f'episodes)')
    return 'RL episodes (the environment steps each used differ: see the training table)'


def write_comparison(out_dir: Path, report: Path, variants: Sequence[str], learned: dict[str, list[str]],
                     drivers: Sequence[str], modes: Sequence[str], training_mode: str, max_steps: int,
                     command: str, budget: dict | None, left_out: Sequence[str] = ()) -> Path:
    """The page at ``report`` and its figures beside it (``<report stem>_*.png``); ``left_out``:
    learned methods of the config this sweep did not train (said on the page)."""
    report.parent.mkdir(parents=True, exist_ok=True)
    per_variant = {variant: variant_runs(out_dir / variant, learned, drivers, modes) for variant in variants}
    per_variant = {variant: runs for variant, runs in per_variant.items() if runs}
    figures = [learning_curves(out_dir / 'training', learned, report.with_name(f'{report.stem}_learning_curves.png'),
                               training_mode),
               variant_figure(per_variant, training_mode, report.with_name(f'{report.stem}_variants.png'))]
    seeds = sorted({len(names) for names in learned.values()})
    sections = ['# Comparison: every method on our highway-exit scenario and its variants',
                (f'Made by `{command}` (nothing on this page is written by hand). Every method is evaluated on '
                 f'every variant on the same test seeds; intervals are 95%, over test seeds.')]
    if learned:
        sections += [
            (f'Learned methods are trained on the base scenario for the mode {training_mode} with '
             f'{" or ".join(map(str, seeds))} seed(s) each, all with the same budget of {budget_words(budget)}; '
             f'a method\'s episodes are averaged over its training seeds per test seed. A row without a suffix '
             f'has our measures (shield, decision interval, lane planner, demonstrations of the rule-based driver '
             f'and pre-training on them). A row <method>{PUBLISHED_SUFFIX} is that baseline as published: it '
             f'learns from its paper\'s reward (config/reward.yaml) with its paper\'s exploration and no '
             f'demonstrations, and drives, in training and here, with only the lanes that exist masked and no '
             f'lane planner; only the decision interval stays ours. Every row is scored under the modes of the '
             f'reward function matrix.'),
            '**Budget** (merged over config/training.yaml for every method alike):\n\n```json\n'
            + json.dumps(budget or {}, indent=2) + '\n```']
    if left_out:
        sections.append(f'Not in this comparison (not trained by this command): {", ".join(left_out)}.')
    sections += [f'![{figure.stem}]({figure.name})' for figure in figures if figure is not None]
    if learned:
        sections.append('## Training wall time\n\n' + '\n'.join(wall_time_lines(out_dir / 'training', learned)))
    for variant, runs in per_variant.items():
        sections.append(f'## {variant}\n\n### Metrics under {training_mode}\n\n' + metrics_table(runs, training_mode))
        winners = winners_table(runs, training_mode)
        if winners:
            sections.append(f'### Who wins which metric ({training_mode}, paired against the runner-up)\n\n'
                            + winners)
        evaluated = [EvaluatedRun(f'{method}_{mode}', episodes, EvaluationResult())
                     for method, by_mode in runs.items() for mode, episodes in by_mode.items()]
        paired = paired_comparison(evaluated, modes, max_steps)
        if paired:
            sections.append('### Against the neutral teacher, every mode\n\n' + comparison_markdown(paired))
        claims = claim_lines(runs, training_mode, {method: len(names) for method, names in learned.items()},
                             run_returns(out_dir / variant, learned, training_mode))
        if claims:
            sections.append(f'### The papers\' claims here (return under {training_mode}, paired)\n\n'
                            'The interval is over test seeds, with each learned method averaged over its training '
                            'runs; "training runs" is the difference between every pair of single runs (each '
                            'run\'s mean over the test seeds), the spread the training seeds add.\n\n'
                            + '\n'.join(claims))
    if len(per_variant) > 1 and next(iter(per_variant)) == variants[0]:
        sections.append(f'## Drop under the variants ({training_mode}; variant minus {variants[0]}, paired by test '
                        f'seed; * the interval excludes 0)\n\n'
                        + drop_table(per_variant, variants[0], training_mode))
    report.write_text('\n\n'.join(sections) + '\n', encoding='utf-8')
    return report
