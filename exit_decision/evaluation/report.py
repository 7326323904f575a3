"""The ``evaluate`` command: runs on fixed test seeds, tables in CSV and Markdown."""
from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.config import ProjectConfig
from exit_decision.env import ExitDecisionEnv
from exit_decision.evaluation.evaluate import EvaluationResult, evaluate
from exit_decision.evaluation.metrics import markdown_table, summarize
from exit_decision.policy import PolicyController, load_policy


def write_episodes(path: Path, result: EvaluationResult) -> None:
    with open(path, 'w', newline='') as stream:
        writer = csv.DictWriter(stream, fieldnames=list(result.episodes[0]))
        writer.writeheader()
        writer.writerows(result.episodes)


def evaluate_runs(config: ProjectConfig, policies: Sequence[Path], drivers: Sequence[str], episodes: int,
                  seed: int, out_dir: Path, command: str) -> str:
    """Evaluate each policy and reference driver on seeds seed..seed+episodes-1.

    Writes per run ``<label>.csv`` (per episode) and ``<label>_actions.csv`` (how often each
    action was chosen), and ``summary.md`` / ``summary.csv`` for all runs."""
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = list(range(seed, seed + episodes))
    rows, summaries = [], []
    for driver in drivers:
        env = ExitDecisionEnv(config, cav_driver='sumo' if driver == 'sumo' else 'policy')
        controller = None if driver == 'sumo' else RuleBasedDriver(
            env.actions, env.shield, env.sim.geometry, config.scenario.road.ramp_speed_limit)
        rows.append((driver, evaluate(env, controller, seeds), env))
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
        write_episodes(out_dir / f'{label}.csv', result)
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
