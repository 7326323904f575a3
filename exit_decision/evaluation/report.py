"""The ``evaluate`` command: runs on fixed test seeds, tables in CSV and Markdown."""
from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from exit_decision.actions import ActionGrid
from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.config import ProjectConfig
from exit_decision.env import ExitDecisionEnv
from exit_decision.evaluation.evaluate import EvaluatedRun, EvaluationResult, evaluate_policy, run_episodes, scored_episodes
from exit_decision.evaluation.metrics import markdown_table, summarize
from exit_decision.evaluation.statistics import paired_interval
from exit_decision.policy import load_policy
from exit_decision.tables import read_rows, write_rows


REFERENCE_DRIVERS = ('sumo', 'rule_based')
TEACHER = 'rule_based'
#: columns of the paired comparison with the teacher (difference run - teacher per seed)
PAIRED_METRICS = ('reward', 'v_AVs', 'p_CAV', 'p_collision_CAV', 'N_braking')


def evaluate_runs(config: ProjectConfig, policies: Sequence[Path], drivers: Sequence[str], modes: Sequence[str],
                  episodes: int, seed: int, out_dir: Path, command: str) -> str:
    """Evaluate each policy and reference driver on seeds seed..seed+episodes-1, scored under
    each named mode's reward.

    A driver or per-mode policy drives once and is scored under every mode; a conditioned
    policy drives at each mode's weights. Writes ``<run>_<mode>.csv`` (per episode; ``reward``
    = the episode's global scalar return under that mode, unscaled), ``<run>_<mode>_actions.csv``,
    ``summary.md`` / ``summary.csv`` (mean and std), and ``comparison.md`` / ``comparison.csv``
    (every run against the neutral teacher under the same mode, paired over seeds)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = list(range(seed, seed + episodes))
    for mode in modes:
        config.mode(mode)
    runs: list[EvaluatedRun] = []
    for driver in drivers:
        env = ExitDecisionEnv(config, mode=modes[0], cav_driver='sumo' if driver == 'sumo' else 'policy')
        try:
            controller = None if driver == 'sumo' else RuleBasedDriver.for_env(env)
            result = EvaluationResult()
            played = run_episodes(env, controller, seeds, result, desc=driver)
        finally:
            env.close()
        runs += [EvaluatedRun(f'{driver}_{mode}', scored_episodes(played, env.reward_fn.weights(config.mode(mode))), result)
                 for mode in modes]
    env = ExitDecisionEnv(config, mode=modes[0])
    try:
        for path in policies:
            runs += evaluate_policy(env, load_policy(path), modes, seeds)
    finally:
        env.close()
    summaries = []
    for run in runs:
        write_rows(out_dir / f'{run.label}.csv', run.episodes)
        summary = summarize(run.episodes)
        if run.result.decisions:
            write_action_counts(out_dir / f'{run.label}_actions.csv', run.result, ActionGrid(config.env.actions))
            summary['shield_overrides'] = (run.result.overrides / run.result.decisions, 0.0)
        summaries.append((run.label, summary))
    table = markdown_table(summaries)
    with open(out_dir / 'summary.csv', 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['run', 'metric', 'mean', 'std'])
        for label, summary in summaries:
            for metric, (mean, std) in summary.items():
                writer.writerow([label, metric, mean, std])
    header = f'# Evaluation on seeds {seeds[0]}..{seeds[-1]} ({episodes} episodes)\n\nMade by `{command}`'
    (out_dir / 'summary.md').write_text(f'{header}; mean ± std over episodes.\n\n{table}\n', encoding='utf-8')
    comparison = paired_comparison(runs, modes, config.scenario.max_steps)
    if comparison:
        write_rows(out_dir / 'comparison.csv', comparison)
        (out_dir / 'comparison.md').write_text(
            f'{header}.\n\n{comparison_markdown(comparison)}\n', encoding='utf-8')
    return table


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
        theirs = {e['seed']: e for e in teacher.episodes}
        for run in runs:
            if not run.label.endswith(f'_{mode}') or run is teacher:
                continue
            row = {'run': run.label[:-len(mode) - 1], 'mode': mode, 'episodes': len(run.episodes),
                   'capped': sum(e['steps'] >= max_steps for e in run.episodes)}
            for metric in PAIRED_METRICS:
                own = np.array([e[metric] for e in run.episodes], dtype=float)
                diff = np.array([e[metric] - theirs[e['seed']][metric] for e in run.episodes], dtype=float)
                mean, low, high = paired_interval(own)
                row.update({metric: mean, f'{metric}_low': low, f'{metric}_high': high})
                mean, low, high = paired_interval(diff)
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


def target_checks(runs: dict[str, dict[str, tuple[float, float]]], modes: Sequence[str] = ('AGGI', 'AGGP', 'CONI', 'CONP'),
                  collision_target: float = 0.01, exit_target: float = 0.95) -> list[str]:
    """The targets and expected orderings of issue 3 / SPEC section 6, checked on the numbers."""
    def value(run: str, metric: str) -> float:
        return runs[run][metric][0]

    lines = []
    for mode in modes:
        run = f'mdgqn_{mode}'
        if run not in runs:
            continue
        collisions, exits = value(run, 'p_collision_CAV'), value(run, 'p_CAV')
        verdict = 'met' if collisions <= collision_target and exits >= exit_target else 'NOT met'
        lines.append(f'- MDGQN {mode}: p_collision_CAV {collisions:.4f} (target <= {collision_target}), '
                     f'p_CAV {exits:.3f} (target >= {exit_target}): {verdict}'
                     + ('' if verdict == 'met' else f' (short by {max(collisions - collision_target, 0):.4f} '
                        f'collisions, {max(exit_target - exits, 0):.3f} p_CAV)'))
    # expected: aggressive faster than conservative, incentive faster than punished
    faster_pairs = (('AGGI', 'CONI'), ('AGGP', 'CONP'), ('AGGI', 'AGGP'), ('CONI', 'CONP'))
    for algorithm in ('mdgqn', 'gqn'):
        for fast, slow in faster_pairs:
            f, s = f'{algorithm}_{fast}', f'{algorithm}_{slow}'
            if f in runs and s in runs:
                holds = value(f, 'v_AVs') > value(s, 'v_AVs')
                lines.append(f'- {algorithm.upper()}: {fast} faster than {slow} '
                             f'({value(f, "v_AVs"):.2f} vs {value(s, "v_AVs"):.2f} m/s): '
                             f'{"holds" if holds else "does not hold"}')
    for mode in modes:
        m, g = f'mdgqn_{mode}', f'gqn_{mode}'
        if m in runs and g in runs:
            better = (value(m, 'p_CAV') - 10 * value(m, 'p_collision_CAV')
                      >= value(g, 'p_CAV') - 10 * value(g, 'p_collision_CAV'))
            lines.append(f'- {mode}: MDGQN at least as good as GQN on p_CAV - 10 p_collision_CAV '
                         f'({value(m, "p_CAV"):.3f}/{value(m, "p_collision_CAV"):.4f} vs '
                         f'{value(g, "p_CAV"):.3f}/{value(g, "p_collision_CAV"):.4f}): '
                         f'{"holds" if better else "does not hold"}')
    reference = 'sumo'
    if reference in runs:
        faster = [f'{a}_{m}' for a in ('mdgqn', 'gqn') for m in ('AGGI', 'AGGP')
                  if f'{a}_{m}' in runs and value(f'{a}_{m}', 'v_AVs') > value(reference, 'v_AVs')
                  and value(f'{a}_{m}', 'p_collision_CAV') <= collision_target]
        lines.append(f'- an aggressive mode faster than the SUMO reference ({value(reference, "v_AVs"):.2f} m/s) '
                     f'at p_collision_CAV <= {collision_target}: '
                     + (f'holds ({", ".join(faster)})' if faster else 'does not hold'))
    return lines


def policy_selection(policies_dir: Path) -> list[str]:
    """Which validation run each shipped policy is (episode 0 = right after pre-training)."""
    from exit_decision.policy import load_policy

    lines = ['Shipped policies (`scripts/train_policies`), each the best of its validation runs '
             '(greedy episodes on validation seeds; episode 0 = right after pre-training on '
             'demonstrations), and the validation p_CAV of every run (episode: p_CAV):', '']
    for path in sorted(policies_dir.glob('*/policy.pt')):
        metadata = load_policy(path).metadata
        validation = metadata.get('validation', {})
        episodes = metadata.get('training', {}).get('validation', {}).get('episodes', '?')
        history = path.parent / 'validation.csv'
        runs = ', '.join(f'{int(float(r["episode"]))}: {float(r["p_CAV"]):.3f}'
                         for r in read_rows(history)) if history.exists() else 'no log'
        lines.append(f'- {path.parent.name}: kept from episode {validation.get("episode", "?"):g} '
                     f'(validation on {episodes} episodes: p_CAV {validation.get("p_CAV", float("nan")):.3f}, '
                     f'p_collision_CAV {validation.get("p_collision_CAV", float("nan")):.3f}); all runs: {runs}'
                     + demonstrator_headway(path.parent / 'config.json'))
    return lines


def demonstrator_headway(run_config: Path) -> str:
    """'; demonstrator headway 1 s' from a run's config.json (the config that made the run)."""
    if not run_config.exists():
        return ''
    run = json.loads(run_config.read_text())
    driver = ProjectConfig.model_validate(run['config']).rule_based(run['mode'])
    return f'; demonstrator headway {driver.time_headway:g} s'


def step_cap_lines(evaluation_dir: Path, max_steps: int) -> list[str]:
    """Per run, the test episodes that ran into the step cap: a CAV stopped on the road held
    the traffic up until the episode was cut (its exit rate alone does not show this)."""
    lines = []
    for path in sorted(evaluation_dir.glob('*.csv')):
        if path.name == 'summary.csv' or path.stem.endswith('_actions'):
            continue
        rows = read_rows(path)
        capped = sum(float(row['steps']) >= max_steps for row in rows)
        if capped:
            lines.append(f'- {path.stem}: {capped} of {len(rows)} episodes ran into the {max_steps}-step cap')
    return lines or [f'- none: no episode ran into the {max_steps}-step cap']


def results_page(evaluation_dir: Path, ablation_csv: Path | None, figures_dir: Path, out: Path,
                 max_steps: int) -> Path:
    """docs/results.md from the generated artefacts: nothing in it is typed by hand."""
    from exit_decision.learning.ablation import markdown as ablation_markdown

    relative = lambda path: Path(path).resolve().relative_to(out.parent.resolve()).as_posix()  # noqa: E731
    summary_md = (evaluation_dir / 'summary.md').read_text().split('\n', 2)
    parts = ['# Results', '',
             'Generated by `exit-decision report` from the outputs of the commands named below; '
             'rerun them to reproduce every number.', '',
             *(['```', (evaluation_dir.parent / 'commands.txt').read_text().strip(), '```', '']
               if (evaluation_dir.parent / 'commands.txt').exists() else []),
             '## Evaluation (test seeds never used in training)', '', summary_md[2].strip(), '',
             f'Per-episode values and action counts: [`{relative(evaluation_dir)}/`]({relative(evaluation_dir)}/).', '',
             *policy_selection(Path('policies')), '',
             '## Episodes cut by the step cap', '', *step_cap_lines(evaluation_dir, max_steps), '',
             '## Targets and expected orderings', '', *target_checks(read_summary(evaluation_dir / 'summary.csv')), '',
             'Each policy above names its demonstrator\'s time headway: where the modes imitate '
             'different demonstrators, the speed orderings between them come from the demonstrators '
             'as much as from the reward matrix. What was tried to reach the targets, with its '
             'measurements: [`design.md`](design.md), sections "Rule-based driver" and "Learning".', '']
    if ablation_csv is not None and ablation_csv.exists():
        parts += ['## Ablation: from the paper taken literally to our setting', '',
                  'Each step adds one measure to the previous (config/ablation.yaml); every step is trained with '
                  'the same short budget and evaluated on the same test seeds, so the table compares the '
                  'measures, not the final quality. Made by `'
                  + ((ablation_csv.parent / 'command.txt').read_text().strip()
                     if (ablation_csv.parent / 'command.txt').exists() else 'exit-decision ablation') + '`.', '',
                  ablation_markdown(ablation_csv), '']
    benchmarks = evaluation_dir.parent / 'benchmarks.txt'
    if benchmarks.exists():
        parts += ['## Speed', '', '```', benchmarks.read_text().strip(), '```', '']
    figures = sorted(figures_dir.glob('*.png'))
    if figures:
        parts += ['## Figures', '', 'Made by `exit-decision plot`.', '']
        parts += [f'![{path.stem}]({relative(path)})' for path in figures]
    out.write_text('\n'.join(parts) + '\n', encoding='utf-8')
    return out
