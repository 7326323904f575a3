"""The trade-off one conditioned checkpoint offers: CAV speed against hard braking and safety.

The policy drives the same seeds at every weight point: the configured modes (the paper's
four and Table A1's), and a sweep between the aggressive and the conservative decision
weights (incentive and punishment 0.5 / 0.5). Per point: mean CAV speed, emergency brakings,
the safety row of the reward (per episode, as scored) and the Exit-1 and collision rates.
Writes ``tradeoff.csv`` and ``tradeoff.png``.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from exit_decision.config import ProjectConfig  # noqa: E402
from exit_decision.errors import PolicyError  # noqa: E402
from exit_decision.reward import SAFETY, weight_input, weights_of_input  # noqa: E402
from exit_decision.tables import write_rows  # noqa: E402

SWEEP_STEPS = 5   # points from aggressive to conservative decision weights


def sweep_ends(config: ProjectConfig) -> tuple[str, str]:
    """The modes whose decision weights the sweep runs between: the matrix's aggressive and
    conservative incentive modes (AGGI and CONI in the shipped config)."""
    return config.mode_matrix.aggressive.incentive, config.mode_matrix.conservative.incentive


def weight_points(config: ProjectConfig) -> dict[str, np.ndarray]:
    points = {name: weight_input(mode) for name, mode in config.modes.items()}
    low, high = (weight_input(config.mode(name))[:4] for name in sweep_ends(config))
    for alpha in np.linspace(0.0, 1.0, SWEEP_STEPS):
        points[f'sweep_{alpha:.2f}'] = np.array([*((1 - alpha) * low + alpha * high), 0.5, 0.5])
    return points


def run_tradeoff(config: ProjectConfig, policy_path: Path, seeds: list[int], out_dir: Path) -> Path:
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.evaluate import run_episodes
    from exit_decision.model.policy import load_controller

    env = ExitDecisionEnv(config)
    rows = []
    try:
        controller = load_controller(config, policy_path, env.shield, env.planner)
        if not controller.policy.conditioned:
            raise PolicyError(f'{policy_path}: the trade-off needs a mode-conditioned policy')
        for name, weights in weight_points(config).items():
            episodes = run_episodes(env, controller.at(weights), seeds, desc=name)
            multipliers = weights_of_input(weights)
            rows.append({'point': name, **{f'w{i}': float(w) for i, w in enumerate(weights)},
                         **{k: float(np.nanmean([e[k] for e in episodes]))
                            for k in ('v_AVs', 'N_braking', 'p_CAV', 'p_collision_CAV')},
                         'safety_row': float(np.mean([e['reward_vector'][SAFETY].sum() for e in episodes])),
                         'return': float(np.mean([(e['reward_vector'] * multipliers).sum() for e in episodes]))})
    finally:
        env.close()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_rows(out_dir / 'tradeoff.csv', rows)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, key, label in ((axes[0], 'N_braking', 'emergency brakings per episode'),
                           (axes[1], 'safety_row', 'safety row of the reward per episode (scaled)')):
        for row in rows:
            sweep = row['point'].startswith('sweep_')
            ax.scatter(row['v_AVs'], row[key], marker='.' if sweep else 'o', color='grey' if sweep else 'tab:blue')
            ax.annotate(row['point'].removeprefix('sweep_'), (row['v_AVs'], row[key]), fontsize=7)
        ax.set_xlabel('mean CAV speed [m/s]')
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle(f'{policy_path.parent.name}: one checkpoint at every weight point ({len(seeds)} seeds each; '
                 f'grey: {"→".join(sweep_ends(config))} decision weights, I/P 0.5/0.5)', fontsize=9)
    fig.tight_layout()
    fig.savefig(out_dir / 'tradeoff.png', dpi=120)
    plt.close(fig)
    return out_dir / 'tradeoff.png'
