"""The ``evaluate`` command: runs on fixed test seeds, tables in CSV and Markdown."""
from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.config import ProjectConfig
from exit_decision.env import ExitDecisionEnv
from exit_decision.evaluation.evaluate import evaluate
from exit_decision.evaluation.metrics import markdown_table, summarize
from exit_decision.policy import PolicyController, load_policy
from exit_decision.tables import read_rows, write_rows


def evaluate_runs(config: ProjectConfig, policies: Sequence[Path], drivers: Sequence[str], episodes: int,
                  seed: int, out_dir: Path, command: str) -> str:
    """Evaluate each policy and reference driver on seeds seed..seed+episodes-1.

    Writes per run ``<label>.csv`` (per episode) and ``<label>_actions.csv`` (how often each
    action was chosen), and ``summary.md`` / ``summary.csv`` for all runs."""
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = list(range(seed, seed + episodes))
    rows, summaries = [], []
    for driver in drivers:
        name, _, mode = driver.partition(':')   # rule_based:AGGI = that mode's demonstrator
        env = ExitDecisionEnv(config, mode=mode or None, cav_driver='sumo' if name == 'sumo' else 'policy')
        controller = None if name == 'sumo' else RuleBasedDriver.for_env(env)
        rows.append((driver.replace(':', '_'), evaluate(env, controller, seeds), env))
        env.close()
    for path in policies:
        policy = load_policy(path)
        env = ExitDecisionEnv(config, mode=policy.metadata['mode'])
        policy.check_compatible(config.graph.max_vehicles, config.graph.feature_set,
                                config.env.decision_interval, env.actions)
        label = f'{policy.metadata["algorithm"]}_{policy.metadata["mode"]}'
        rows.append((label, evaluate(env, PolicyController(policy, env.shield), seeds), env))
        env.close()
    for label, result, env in rows:
        write_rows(out_dir / f'{label}.csv', result.episodes)
        summary = summarize(result.episodes)
        summaries.append((label, summary))
        if result.decisions:
            with open(out_dir / f'{label}_actions.csv', 'w', newline='') as stream:
                writer = csv.writer(stream)
                writer.writerow(['lane_change', 'acceleration', 'count', 'share'])
                total = result.action_counts.sum()
                for index in np.flatnonzero(result.action_counts):
                    writer.writerow([env.actions.lane_change_of[index], env.actions.acceleration_of[index],
                                     result.action_counts[index], result.action_counts[index] / total])
            summary['shield_overrides'] = (result.overrides / result.decisions, 0.0)
    table = markdown_table(summaries)
    with open(out_dir / 'summary.csv', 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['run', 'metric', 'mean', 'std'])
        for label, summary in summaries:
            for metric, (mean, std) in summary.items():
                writer.writerow([label, metric, mean, std])
    (out_dir / 'summary.md').write_text(
        f'# Evaluation on seeds {seeds[0]}..{seeds[-1]} ({episodes} episodes)\n\n'
        f'Made by `{command}`; mean ± std over episodes.\n\n{table}\n', encoding='utf-8')
    return table


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
