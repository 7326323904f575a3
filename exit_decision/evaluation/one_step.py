"""One-step gains over the prior (issue 39): what one different option, begun once by one CAV
where the prior chooses, changes in the episode's return, the prior driving everything else.

At ``points`` random choice points of each seed's prior episode, every allowed option is begun
there in turn (the prior's own too: a control, which must gain exactly 0), then the prior drives
to the end on the same seed. The return difference under the mode's weights is a paired, unbiased
sample of the one-step advantage Q_prior(s, o) - V_prior(s). If no option gains anywhere, the prior
is optimal over the options (the policy-improvement theorem): no learner over them can beat it.

The best option of a point is a maximum over single realisations, biased upward by their noise.
``fresh_future_gains`` measures the best ones again on fresh futures from the same point (the
insertions to come redrawn, the human drivers' hidden speed factors perturbed), each paired with
the prior on the same future: the mean of those is an unbiased estimate of what the selected
option gains, the part a learner, who sees the graph and not the seed, could take.
"""
from __future__ import annotations

from collections.abc import Sequence
from itertools import count

import numpy as np
from tqdm import tqdm

from exit_decision.agents.options import OptionSpace
from exit_decision.driving.episode import play_episode
from exit_decision.driving.prior import PriorDriver, PriorTable
from exit_decision.env import ExitDecisionEnv
from exit_decision.evaluation.statistics import t_interval
from exit_decision.model.modes import Mode
from exit_decision.reward import scalar


def _return_with(env: ExitDecisionEnv, table: PriorTable, space: OptionSpace, mode: Mode, weights: np.ndarray,
                 seed: int, point: int | None = None, option: int | None = None,
                 future: tuple[int, float] | None = None, masks: list[np.ndarray] | None = None) -> float:
    """The return of ``seed``'s prior episode with ``option`` begun at choice ``point`` (None: the
    prior's own); with ``future`` = (seed, speed factor sd) the future is perturbed there
    (``HighwaySimulation.perturb_future``); ``masks`` collects every choice's allowed options."""
    begun = count()   # the choices of this episode, in order (after the point it may make more)

    def explore(mask: np.ndarray) -> int | None:
        if masks is not None:
            masks.append(mask.copy())
        if next(begun) != point:
            return None
        if future is not None:
            env.sim.perturb_future(*future)
        return option

    play_episode(env, PriorDriver(table, space, mode, explore=explore), seed)
    return float(scalar(env.episode_log.reward_vector, weights))


def one_step_gains(env: ExitDecisionEnv, table: PriorTable, mode: Mode, weights: np.ndarray, seeds: Sequence[int],
                   points: int, rng: np.random.Generator, desc: str | None = None) -> list[dict]:
    """Per seed, choice point and allowed option: the return of the episode in which that option
    is begun at that point, minus the prior's (``weights``: the scoring mode's multipliers)."""
    space = OptionSpace(env.config, env.shield, env.planner)
    prior = table.best_option(space, mode.weights)
    rows = []
    for seed in tqdm(seeds, desc=desc, unit='seed', disable=desc is None):
        masks: list[np.ndarray] = []
        base = _return_with(env, table, space, mode, weights, seed, masks=masks)
        for point in sorted(rng.choice(len(masks), size=min(points, len(masks)), replace=False).tolist()):
            for option in np.flatnonzero(masks[point]).tolist():
                chosen = space.options[option]
                gain = _return_with(env, table, space, mode, weights, seed, point, option) - base
                rows.append({'seed': seed, 'point': point, 'choices': len(masks), 'option': option,
                             'lane_intent': chosen.lane_intent, 'style': chosen.style, 'prior': option == prior,
                             'gain': gain})
    return rows


def fresh_future_gains(env: ExitDecisionEnv, table: PriorTable, mode: Mode, weights: np.ndarray,
                       rows: Sequence[dict], futures: int, top: int, speed_factor_sd: float,
                       desc: str | None = None) -> list[dict]:
    """The ``top`` deviations of each point of ``rows`` (``one_step_gains``'s) that gained most,
    each on ``futures`` fresh futures from that point, minus the prior on the same future."""
    space = OptionSpace(env.config, env.shield, env.planner)
    by_point: dict[tuple[int, int], list[dict]] = {}
    for row in rows:
        if not row['prior']:
            by_point.setdefault((row['seed'], row['point']), []).append(row)
    out = []
    for (seed, point), deviations in tqdm(by_point.items(), desc=desc, unit='point', disable=desc is None):
        chosen = sorted(deviations, key=lambda row: row['gain'], reverse=True)[:top]
        for future in range(futures):
            perturbed = (int(np.random.SeedSequence([seed, point, future]).generate_state(1)[0]), speed_factor_sd)
            base = _return_with(env, table, space, mode, weights, seed, point, None, perturbed)
            for rank, row in enumerate(chosen):
                gain = _return_with(env, table, space, mode, weights, seed, point, row['option'], perturbed) - base
                out.append({'seed': seed, 'point': point, 'rank': rank, 'option': row['option'],
                            'lane_intent': row['lane_intent'], 'style': row['style'], 'future': future,
                            'prior_return': base, 'first_gain': row['gain'], 'gain': gain})
    return out


def summary(rows: Sequence[dict]) -> dict[str, float]:
    """The control's largest |gain| (0: the pairing holds), the mean gain of a deviation, the share
    that gains, and per point the best deviation's gain: mean, median, share above 0.05."""
    control = [abs(row['gain']) for row in rows if row['prior']]
    deviations = np.array([row['gain'] for row in rows if not row['prior']])
    best: dict[tuple, float] = {}
    for row in rows:
        if not row['prior']:
            key = (row['seed'], row['point'])
            best[key] = max(best.get(key, -np.inf), row['gain'])
    per_point = np.array(list(best.values()))
    return {'points': len(per_point), 'deviations': len(deviations), 'control': max(control, default=float('nan')),
            'mean_gain': float(deviations.mean()), 'share_gaining': float((deviations > 0).mean()),
            'best_mean': float(per_point.mean()), 'best_median': float(np.median(per_point)),
            'best_above_0.05': float((per_point > 0.05).mean())}


def fresh_points(rows: Sequence[dict]) -> list[dict]:
    """Per point of ``fresh_future_gains``'s rows (as returned, or read back from its CSV), its best
    deviation (rank 0): the first gain, the fresh futures' mean gain with its t interval, and the
    spread (sd) of the prior's own return between the futures."""
    per_point: dict[tuple, list[dict]] = {}
    for row in rows:
        if int(row['rank']) == 0:
            per_point.setdefault((row['seed'], row['point']), []).append(row)
    return [{'first': float(found[0]['first_gain']),
             'fresh': t_interval([float(row['gain']) for row in found]),
             'prior_spread': float(np.std([float(row['prior_return']) for row in found], ddof=1))}
            for found in per_point.values()]


def fresh_summary(rows: Sequence[dict]) -> dict[str, float]:
    """``points_summary`` of ``fresh_future_gains``'s rows."""
    return points_summary(fresh_points(rows))


def points_summary(points: Sequence[dict]) -> dict[str, float]:
    """Of each point's best deviation (``fresh_points``): its first gain (the biased maximum) and
    its mean gain on the fresh futures, averaged over points with a 95% interval, and their median
    (one future with a collision moves the mean by itself); the share of points whose fresh gain is
    resolved above 0 (t interval over the futures); and how much the prior's own return moves
    between futures (0 would mean the futures are not fresh)."""
    means = [point['fresh'][0] for point in points]
    mean, low, high = t_interval(means)
    return {'points': len(points), 'first_mean': float(np.mean([point['first'] for point in points])),
            'fresh_mean': mean, 'fresh_low': low, 'fresh_high': high, 'fresh_median': float(np.median(means)),
            'resolved_share': float(np.mean([point['fresh'][1] > 0 for point in points])),
            'prior_spread': float(np.mean([point['prior_spread'] for point in points]))}
