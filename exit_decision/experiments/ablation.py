"""The ablation: train and evaluate each cumulative step of config/ablation.yaml.

A step is a name, a config override (merged over the files and the earlier steps) and
optionally ``train_mode: conditioned`` (that step trains the one mode-conditioned network;
every step is evaluated at the ablation's mode, against the same test seeds)."""
from __future__ import annotations

import shutil
from pathlib import Path

from exit_decision.config import ConfigError, default_config_dir, deep_merge, load_project, load_yaml
from exit_decision.env import ExitDecisionEnv
from exit_decision.evaluation.evaluate import evaluate_policy
from exit_decision.evaluation.metrics import summarize
from exit_decision.learning.trainer import Trainer
from exit_decision.tables import read_rows, write_rows

#: the ablation's short runs validate less often, on fewer episodes, than the shipped policies
ABLATION_VALIDATION = {'training': {'validation': {'every_episodes': 20, 'episodes': 5}}}
COLUMNS = ('p_CAV', 'p_collision_CAV', 'p_collision', 'v_AVs', 'N_braking', 'reward')


def ablation_steps(path: Path) -> list[tuple[str, dict, str | None]]:
    """(name, cumulative override, training mode: None = the ablation's mode) per step."""
    data = load_yaml(path)
    if not isinstance(data, dict) or not isinstance(data.get('steps'), list):
        raise ConfigError(f'{path}: expected a list under "steps"')
    steps, override, train_mode = [], {}, None
    for index, step in enumerate(data['steps']):
        if not isinstance(step, dict) or not {'name', 'override'} <= set(step) <= {'name', 'override', 'train_mode'}:
            raise ConfigError(f'{path}: steps.{index}: needs "name" and "override" (and may have "train_mode")')
        override = deep_merge(override, step['override'])
        train_mode = step.get('train_mode', train_mode)
        steps.append((step['name'], override, train_mode))
    return steps


def run_ablation(out_dir: Path, algorithm: str, mode: str, episodes: int, eval_episodes: int, seed: int,
                 test_seed: int, only: list[int] | None = None, config_dir: Path | None = None) -> Path:
    """Train each step for ``episodes`` episodes, evaluate its best policy on the test seeds;
    one row per step in ``ablation.csv`` (a step run again replaces its row)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    directory = config_dir or default_config_dir()
    table = out_dir / 'ablation.csv'
    for index, (name, override, train_mode) in enumerate(ablation_steps(directory / 'ablation.yaml')):
        if only and index not in only:
            continue
        config = load_project(directory, overrides=[override, ABLATION_VALIDATION])
        run_dir = out_dir / f'step{index}'
        shutil.rmtree(run_dir, ignore_errors=True)   # a step that is run again starts afresh
        policy_path = Trainer(config, algorithm, train_mode or mode, seed, run_dir).run(episodes)
        env = ExitDecisionEnv(config, mode=mode)
        try:
            (run,) = evaluate_policy(env, policy_path, [mode],
                                     list(range(test_seed, test_seed + eval_episodes)))
        finally:
            env.close()
        summary = summarize(run.episodes)
        row = {'step': index, 'name': name, 'episodes': episodes, 'test_episodes': eval_episodes,
               **{f'{c}_mean': summary[c][0] for c in COLUMNS}, **{f'{c}_std': summary[c][1] for c in COLUMNS}}
        earlier = [r for r in read_rows(table) if int(r['step']) != index] if table.exists() else []
        write_rows(table, sorted([*earlier, row], key=lambda r: int(r['step'])))
    return table


def markdown(table: Path) -> str:
    rows = sorted(read_rows(table), key=lambda r: int(r['step']))
    lines = ['| step | ' + ' | '.join(COLUMNS) + ' |', '|---' * (len(COLUMNS) + 1) + '|']
    for row in rows:
        cells = [f'{float(row[c + "_mean"]):.3g} ± {float(row[c + "_std"]):.2g}' for c in COLUMNS]
        lines.append(f'| {row["step"]}. {row["name"]} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)
