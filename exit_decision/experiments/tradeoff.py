"""The trade-off one conditioned checkpoint offers: CAV speed against hard braking and safety.

The policy drives the same seeds at every weight point: the configured modes (the paper's
four and Table A1's), and a sweep between the aggressive and the conservative decision
weights (incentive and punishment 0.5 / 0.5). Per point: mean CAV speed, emergency brakings,
the safety row of the reward (per episode, as scored) and the Exit-1 and collision rates.
Writes ``tradeoff.csv`` and ``tradeoff.png``; ``redraw_tradeoff`` draws the figure again from the
CSV alone (``exit-decision tradeoff --plot-only``).
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
from exit_decision.tables import read_rows, write_rows  # noqa: E402

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
    from exit_decision.driving.policy import policy_driver
    from exit_decision.evaluation.evaluate import play_episodes
    from exit_decision.model.modes import ModeWeights
    from exit_decision.model.policy import ACTION_SPACES, load_controller

    env = ExitDecisionEnv(config)
    rows = []
    try:
        controller = load_controller(config, policy_path, env.shield, env.planner, action_spaces=ACTION_SPACES)
        if not controller.policy.conditioned:
            raise PolicyError(f'{policy_path}: the trade-off needs a mode-conditioned policy')
        driver, modes = policy_driver(controller, config), ModeWeights(config)
        for name, weights in weight_points(config).items():
            driver.set_mode(modes.of_weights(weights))
            episodes = play_episodes(env, driver, seeds, desc=name)
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
    return tradeoff_figure(rows, out_dir / 'tradeoff.png', figure_title(config, policy_path, len(seeds)))


def figure_title(config: ProjectConfig, policy_path: Path, seeds: int) -> str:
    return (f'{policy_path.parent.name}: one checkpoint at every weight point ({seeds} seeds each; '
            f'grey: {"→".join(sweep_ends(config))} decision weights, I/P 0.5/0.5)')


def redraw_tradeoff(config: ProjectConfig, policy_path: Path, seeds: int, out_dir: Path) -> Path:
    """``tradeoff.png`` again from ``out_dir``'s tradeoff.csv: no simulation, no checkpoint read
    (``policy_path`` and ``seeds`` only name them in the title)."""
    rows = [{key: value if key == 'point' else float(value) for key, value in row.items()}
            for row in read_rows(out_dir / 'tradeoff.csv')]
    return tradeoff_figure(rows, out_dir / 'tradeoff.png', figure_title(config, policy_path, seeds))


#: where a point's name may go, in points from it (right above first); the first that overlaps
#: no name placed before and no other point is taken
LABEL_OFFSETS = ((4, 3), (4, -9), (-4, 3), (-4, -9), (4, 9), (4, -15), (-4, 9), (-4, -15))


def tradeoff_figure(rows: list[dict], path: Path, title: str) -> Path:
    """CAV speed against emergency brakings and against the safety row, one point per weight
    point (the sweep in grey, joined in its order), each named where its name covers no other."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    sweep = [row for row in rows if row['point'].startswith('sweep_')]
    for ax, key, label in ((axes[0], 'N_braking', 'emergency brakings per episode'),
                           (axes[1], 'safety_row', 'safety row of the reward per episode (scaled)')):
        ax.plot([r['v_AVs'] for r in sweep], [r[key] for r in sweep], color='grey', lw=0.8, alpha=0.6, zorder=1)
        for row in rows:
            grey = row['point'].startswith('sweep_')
            ax.scatter(row['v_AVs'], row[key], s=20 if grey else 40, color='grey' if grey else 'tab:blue', zorder=2)
        ax.set_xlabel('mean CAV speed [m/s]')
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.margins(0.12)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    for ax, key in zip(axes, ('N_braking', 'safety_row')):
        place_names(ax, [(row['point'].removeprefix('sweep_'), row['v_AVs'], row[key]) for row in rows])
    fig.savefig(path, dpi=120, bbox_inches='tight', pad_inches=0.1)
    plt.close(fig)
    return path


def place_names(ax, points: list[tuple[str, float, float]], fontsize: float = 7) -> None:
    """Each point's name beside it, at the first of LABEL_OFFSETS where its box overlaps no name
    placed before and no other point (the last offset when every one does)."""
    renderer = ax.figure.canvas.get_renderer()
    ax.figure.canvas.draw()   # the axes' limits and place, final
    dots = [(px - 6, py - 6, px + 6, py + 6) for px, py in (ax.transData.transform((x, y)) for _, x, y in points)]
    placed: list[tuple[float, float, float, float]] = []

    def clear(box: tuple[float, float, float, float], own: int) -> bool:
        others = placed + dots[:own] + dots[own + 1:]
        return not any(box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3] for o in others)
    for index, (name, x, y) in enumerate(points):
        for dx, dy in LABEL_OFFSETS:
            text = ax.annotate(name, (x, y), xytext=(dx, dy), textcoords='offset points', fontsize=fontsize,
                               ha='left' if dx > 0 else 'right', va='bottom')
            extent = text.get_window_extent(renderer)
            box = (extent.x0 - 2, extent.y0 - 1, extent.x1 + 2, extent.y1 + 1)
            if clear(box, index) or (dx, dy) == LABEL_OFFSETS[-1]:
                placed.append(box)
                break
            text.remove()
