"""PNG figures like paper 000's (and paper 001's action distribution), from run outputs.

- ``training_reward.png`` (Fig. 5): episode reward during training per mode, GQN vs MDGQN.
- ``reward_comparison.png`` (Fig. 4): reward matrix vs baseline reward, training curves of
  the same mode normalised to [0, 1] by each curve's own min and max.
- ``test_reward.png`` (Fig. 6, as differences): per mode, each driver's test return minus the
  neutral rule-based driver's on the same seeds, mean with its 95% interval.
- ``speeds.png`` (Fig. 7): per mode, mean speed of CAVs and of all traffic per driver.
- ``actions_<run>.png`` (paper 001 Fig. 20): how often each action was chosen.
- ``validation_<run>.png``: the learning curve judged against the teacher: per validation
  mode, the candidate's mean paired return gain over the neutral rule-based teacher (the
  teacher's level is the line at 0) and its Exit-1 rate against the target.
- ``one_step_fresh_futures.png``: per mode, each choice point's best option over the prior, its
  gain on the first look (one realisation) against its mean gain on fresh futures, with 95%
  intervals: what is left of the maximum once its noise is gone (``one-step-gains --futures``).
"""
from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from exit_decision.evaluation.report import REFERENCE_DRIVERS, TEACHER  # noqa: E402
from exit_decision.evaluation.statistics import last_third_slopes, paired_differences, paired_interval  # noqa: E402
from exit_decision.model.names import described  # noqa: E402
from exit_decision.tables import read_rows  # noqa: E402

SMOOTHING = 10   # episodes in the rolling mean of training curves
SYMLOG_GAIN = 0.01   # one-step gains: linear within this, logarithmic beyond
REFERENCE = TEACHER   # the driver test returns are drawn against


def read_csv(path: Path) -> dict[str, np.ndarray]:
    """Columns of a numeric CSV as arrays."""
    rows = read_rows(path)
    return {key: np.array([float(row[key]) for row in rows]) for key in rows[0]} if rows else {}


def save(fig: plt.Figure, path: Path, layout: bool = True) -> Path:
    """The figure as a PNG, laid out (unless ``layout`` is False: the caller did) and cropped to
    what it draws, so no label is cut."""
    if layout:
        fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches='tight', pad_inches=0.1)
    plt.close(fig)
    return path


def rolling(values: np.ndarray, window: int = SMOOTHING) -> np.ndarray:
    if len(values) < window:
        return values
    kernel = np.ones(window) / window
    return np.convolve(values, kernel, mode='valid')


def run_info(run_dir: Path) -> dict:
    info = json.loads((run_dir / 'config.json').read_text())
    info['reward_variant'] = info['config']['env']['reward_variant']
    return info


def training_reward(run_dirs: list[Path], out: Path) -> Path | None:
    """Per mode, each run's episode reward while it trained (the runs named in the title)."""
    named = [(d.name, run_info(d), read_csv(d / 'training.csv')) for d in run_dirs if (d / 'training.csv').exists()]
    named = [(name, info, data) for name, info, data in named if info['reward_variant'] != 'baseline']
    runs = [(info, data) for _, info, data in named]
    if not runs:
        return None
    modes = sorted({info['mode'] for info, _ in runs})
    fig, axes = plt.subplots(1, len(modes), figsize=(4 * len(modes), 3.2), squeeze=False)
    for ax, mode in zip(axes[0], modes):
        for info, data in runs:
            if info['mode'] == mode:
                ax.plot(rolling(data['reward']), label=info['algorithm'].upper())
        ax.set_title(mode)
        ax.set_xlabel('episode')
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(f'episode reward ({SMOOTHING}-episode mean)')
    axes[0][0].legend()
    fig.suptitle(', '.join(described(name) for name, _, _ in named) + ': training (exploring)', fontsize=10)
    return save(fig, out / 'training_reward.png')


def reward_comparison(run_dirs: list[Path], out: Path) -> Path | None:
    runs = [(run_info(d), read_csv(d / 'training.csv')) for d in run_dirs if (d / 'training.csv').exists()]
    baseline = [(i, d) for i, d in runs if i['reward_variant'] == 'baseline']
    if not baseline:
        return None
    info, data = baseline[0]
    matrix = [(i, d) for i, d in runs if i['reward_variant'] != 'baseline'
              and i['mode'] == info['mode'] and i['algorithm'] == info['algorithm']]
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for label, curve in [('baseline reward', data['reward'])] + [
            (f'reward matrix ({i["reward_variant"]})', d['reward']) for i, d in matrix]:
        smooth = rolling(curve)
        span = smooth.max() - smooth.min()
        ax.plot((smooth - smooth.min()) / span if span else smooth * 0, label=label)
    ax.set_title(f'{info["algorithm"].upper()} {info["mode"]}: normalised training reward')
    ax.set_xlabel('episode')
    ax.set_ylabel('normalised reward')
    ax.legend()
    ax.grid(alpha=0.3)
    return save(fig, out / 'reward_comparison.png')


def evaluation_runs(evaluation_dir: Path) -> dict[str, dict[str, np.ndarray]]:
    return {path.stem: read_csv(path) for path in sorted(evaluation_dir.glob('*.csv'))
            if path.stem not in ('summary', 'comparison') and not path.stem.endswith('_actions')}


def validation_curves(run_dir: Path, out: Path, exit_target: float = 0.99) -> Path | None:
    """Per validation mode: gain over the teacher (with its 95% interval) and Exit-1 rate."""
    path = run_dir / 'validation.csv'
    rows = read_rows(path) if path.exists() else []
    if not rows or 'gain' not in rows[0]:
        return None
    fig, (gain_ax, exit_ax) = plt.subplots(1, 2, figsize=(10, 3.4))
    slopes = last_third_slopes(rows)
    for mode in dict.fromkeys(row['mode'] for row in rows):
        own = [row for row in rows if row['mode'] == mode]
        episodes = [int(row['episode']) for row in own]
        gains = np.array([float(row['gain']) for row in own])
        line, = gain_ax.plot(episodes, gains, marker='o', label=mode)
        fitted = slopes[mode]
        if np.isfinite(fitted['slope']):   # the last third's fitted line (has the curve flattened?)
            last = np.array([e for e in episodes if e >= fitted['from_episode']])
            mean_x, mean_y = last.mean(), np.mean([g for e, g in zip(episodes, gains) if e >= fitted['from_episode']])
            gain_ax.plot(last, mean_y + fitted['slope'] * (last - mean_x), color=line.get_color(), linestyle=':')
        gain_ax.fill_between(episodes, [float(row['gain_low']) for row in own],
                             [float(row['gain_high']) for row in own], alpha=0.15)
        exit_ax.plot(episodes, [float(row['p_CAV']) for row in own], marker='o', label=mode)
    described_run = run_dir / 'config.json'
    options = described_run.exists() and json.loads(described_run.read_text()).get('action_space') == 'options'
    gain_ax.axhline(0.0, color='black', linestyle='--',
                    label='teacher: the best fixed driver' if options else 'teacher (neutral rule-based)')
    gain_ax.set_ylabel('return − teacher (validation, paired)')
    gain_ax.set_title('dotted: the last third\'s fitted line', fontsize=8)
    exit_ax.axhline(exit_target, color='red', linestyle=':', label=f'target {exit_target:g}')
    if 'teacher_p_CAV' in rows[0]:
        exit_ax.axhline(float(rows[0]['teacher_p_CAV']), color='black', linestyle='--', label='teacher')
    exit_ax.set_ylabel('Exit-1 rate (validation)')
    for ax in (gain_ax, exit_ax):
        ax.set_xlabel('training episode (0 = after pre-training)')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f'{described(run_dir.name)}: validation against the teacher')
    return save(fig, out / f'validation_{run_dir.name}.png')


def driver_and_mode(label: str, modes: set[str]) -> tuple[str, str]:
    """``rule_based_headway_0.8_AGGI`` -> (``rule_based_headway_0.8``, ``AGGI``) when AGGI is one of
    ``modes``; a label without a mode suffix is its own driver under mode ''."""
    driver, _, mode = label.rpartition('_')
    return (driver, mode) if driver and mode in modes else (label, '')


def runs_by_mode(labels: list[str]) -> tuple[list[str], list[str]]:
    """The modes (suffixes shared by several runs, in order) and the drivers (in order) of
    evaluation runs named ``<driver>_<mode>``."""
    suffixes = [label.rpartition('_')[2] for label in labels]
    modes = [m for m in dict.fromkeys(suffixes) if suffixes.count(m) > 1] or ['']
    drivers = list(dict.fromkeys(driver_and_mode(label, set(modes))[0] for label in labels))
    return modes, drivers


def mode_panels(modes: list[str], drivers: list[str], width: float = 3.2):
    """One panel per mode, side by side, the drivers as rows (labels on the first panel only)."""
    fig, axes = plt.subplots(1, len(modes), figsize=(width * len(modes) + 2.0, 0.45 * len(drivers) + 1.6),
                             sharey=True, squeeze=False)
    for ax, mode in zip(axes[0], modes):
        ax.set_yticks(range(len(drivers)), drivers)
        ax.set_ylim(len(drivers) - 0.5, -0.5)   # the first driver on top
        ax.set_title(mode or 'every run', fontsize=10)
        ax.grid(alpha=0.3, axis='x')
    return fig, axes[0]


def learned(drivers: list[str]) -> str:
    """The learned policies among an evaluation's drivers (the rest are reference drivers), for a title."""
    names = [d for d in drivers if d not in REFERENCE_DRIVERS and not d.startswith(TEACHER + '_')]
    return ', '.join(map(described, names)) or 'the reference drivers'


def _rows(columns: dict) -> list[dict]:
    """A run's seed and reward columns as rows (``statistics.paired_differences`` pairs rows)."""
    return [{'seed': seed, 'reward': reward} for seed, reward in zip(columns['seed'], columns['reward'])]


def test_reward(evaluation_dir: Path, out: Path, reference: str = REFERENCE) -> Path | None:
    """Per mode, each driver's test return minus the reference driver's on the same seeds (mean
    and 95% interval; the reference is the line at 0, its mean return in the panel's title),
    the axis on the differences; without the reference, each driver's return (mean, 95%)."""
    runs = evaluation_runs(evaluation_dir)
    if not runs:
        return None
    modes, drivers = runs_by_mode(list(runs))
    label_of = {driver_and_mode(label, set(modes)): label for label in runs}
    has_reference = all((reference, mode) in label_of for mode in modes)
    shown = [d for d in drivers if d != reference] if has_reference else drivers
    if not shown:
        return None
    fig, axes = mode_panels(modes, shown)
    for ax, mode in zip(axes, modes):
        if has_reference:
            ref = runs[label_of[reference, mode]]
            ax.axvline(0.0, color='black', lw=1.0)
            ax.set_title(f'{mode} ({reference}: {np.mean(ref["reward"]):.2f})' if mode else
                         f'{reference}: {np.mean(ref["reward"]):.2f}', fontsize=10)
        for row, driver in enumerate(shown):
            data = runs.get(label_of.get((driver, mode), ''))
            if data is None:
                continue
            values = paired_differences(_rows(data), _rows(ref), 'reward') if has_reference else data['reward']
            mean, low, high = paired_interval(values)
            if np.isfinite(low):
                ax.plot([low, high], [row, row], color='tab:blue', lw=2.5, solid_capstyle='butt')
            ax.plot(mean, row, 'o', color='tab:blue')
        ax.set_xlabel(f'return − {reference} (paired)' if has_reference else 'test episode return')
        ax.margins(x=0.15)
    fig.suptitle(f'{learned(drivers)}: test episodes, mean with 95% interval over the seeds'
                 + (f'; 0 = the {reference} driver on the same seeds' if has_reference else ''), fontsize=10)
    return save(fig, out / 'test_reward.png')


def speeds(evaluation_dir: Path, out: Path) -> Path | None:
    """Per mode, each driver's mean speed of the CAVs and of all vehicles (mean over episodes,
    ± one standard deviation), the axis on the speeds."""
    runs = evaluation_runs(evaluation_dir)
    if not runs:
        return None
    modes, drivers = runs_by_mode(list(runs))
    label_of = {driver_and_mode(label, set(modes)): label for label in runs}
    fig, axes = mode_panels(modes, drivers)
    for ax, mode in zip(axes, modes):
        for offset, (key, name, colour) in zip((-0.15, 0.15), (('v_AVs', 'CAVs', 'tab:blue'),
                                                                ('v_s', 'all vehicles', 'tab:orange'))):
            rows = [(row, runs[label_of[driver, mode]][key]) for row, driver in enumerate(drivers)
                    if (driver, mode) in label_of]
            ax.errorbar([v.mean() for _, v in rows], [row + offset for row, _ in rows],
                        xerr=[v.std() for _, v in rows], fmt='o', capsize=3, color=colour, label=name)
        ax.set_xlabel('mean speed [m/s], ± sd over episodes')
    axes[0].figure.legend(*axes[0].get_legend_handles_labels(), loc='upper center', ncol=2, fontsize=9,
                          frameon=False, bbox_to_anchor=(0.5, 1.0), title=f'{learned(drivers)}: test episodes')
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    return save(fig, out / 'speeds.png', layout=False)


def action_distributions(evaluation_dir: Path, out: Path) -> list[Path]:
    paths, seen = [], set()
    for source in sorted(evaluation_dir.glob('*_actions.csv')):
        content = source.read_bytes()
        if content in seen:
            continue   # the same episodes scored under another mode: the same actions
        seen.add(content)
        data = read_csv(source)
        accelerations = np.unique(data['acceleration'])
        grid = np.zeros((3, len(accelerations)))
        for lc, acc, share in zip(data['lane_change'], data['acceleration'], data['share']):
            grid[int(lc) + 1, np.searchsorted(accelerations, acc)] = share
        fig, ax = plt.subplots(figsize=(7, 2.6))
        image = ax.imshow(grid, aspect='auto', cmap='viridis')
        ax.set_yticks([0, 1, 2], ['right', 'keep', 'left'])
        step = max(1, len(accelerations) // 10)
        ax.set_xticks(range(0, len(accelerations), step), [f'{a:g}' for a in accelerations[::step]])
        ax.set_xlabel('acceleration [m/s²] (chosen values only)')
        run, _, mode = source.stem.removesuffix('_actions').rpartition('_')
        ax.set_title(f'{described(run)} under {mode}: share of the grid\'s actions chosen')
        fig.colorbar(image, ax=ax)
        paths.append(save(fig, out / f'actions_{source.stem.removesuffix("_actions")}.png'))
    return paths


def fresh_futures(gains_dir: Path, out: Path) -> Path | None:
    """Per mode of ``gains_dir``/fresh_futures.csv: each point's best option (rank 0), its first
    gain (x) against its mean gain on the fresh futures (y, 95% interval over the futures)."""
    from exit_decision.evaluation.one_step import fresh_points, points_summary   # the simulation's imports: here only

    rows = read_rows(gains_dir / 'fresh_futures.csv')
    if not rows:
        return None
    modes = list(dict.fromkeys(row['mode'] for row in rows))
    fig, axes = plt.subplots(1, len(modes), figsize=(3.4 * len(modes), 3.4), squeeze=False)
    for ax, mode in zip(axes[0], modes):
        of_mode = [row for row in rows if row['mode'] == mode]
        points = fresh_points(of_mode)
        figures = points_summary(points)
        first = np.array([point['first'] for point in points])
        fresh = np.array([point['fresh'] for point in points])
        ax.errorbar(first, fresh[:, 0], yerr=[fresh[:, 0] - fresh[:, 1], fresh[:, 2] - fresh[:, 0]], fmt='o',
                    markersize=3, capsize=2, color='tab:blue', alpha=0.8)
        low, high = min(first.min(), fresh[:, 1].min()), max(first.max(), fresh[:, 2].max())
        ax.plot([low, high], [low, high], ':', color='grey', label='fresh = first')
        ax.axhline(0.0, color='black', linewidth=0.8)
        ax.set_title(f'{mode}: {len(first)} points\nfresh mean {figures["fresh_mean"]:+.3f} '
                     f'[{figures["fresh_low"]:+.3f}, {figures["fresh_high"]:+.3f}], '
                     f'median {figures["fresh_median"]:+.3f}', fontsize=8)
        ax.set_xscale('symlog', linthresh=SYMLOG_GAIN)   # gains of 0.01 and a collision's 20 on one axis
        ax.set_yscale('symlog', linthresh=SYMLOG_GAIN)
        ax.set_xlabel('gain on the first look')
    axes[0][0].set_ylabel('mean gain on fresh futures (95%)')
    axes[0][0].legend(fontsize=7, loc='upper left')
    return save(fig, out / 'one_step_fresh_futures.png')


def make_all(run_dirs: list[Path], evaluation_dir: Path | None, out: Path, gains_dir: Path | None = None) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    made = [training_reward(run_dirs, out), reward_comparison(run_dirs, out)]
    made += [validation_curves(run_dir, out) for run_dir in run_dirs]
    if evaluation_dir is not None:
        made += [test_reward(evaluation_dir, out), speeds(evaluation_dir, out)]
        made += action_distributions(evaluation_dir, out)
    if gains_dir is not None:
        made.append(fresh_futures(gains_dir, out))
    return [path for path in made if path is not None]
