"""One-step gains over the prior (issue 39): what one different option, begun once by one CAV
where the prior chooses, changes in the episode's return, the prior driving everything else.

At ``points`` random choice points of each seed's prior episode, every allowed option is begun
there in turn (the prior's own too: a control, which must gain exactly 0), then the prior drives
to the end on the same seed. The return difference under the mode's weights is a paired, unbiased
sample of the one-step advantage Q_prior(s, o) - V_prior(s). If no option gains anywhere, the prior
is optimal over the options (the policy-improvement theorem): no learner over them can beat it.
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
from exit_decision.model.modes import Mode
from exit_decision.reward import scalar


def one_step_gains(env: ExitDecisionEnv, table: PriorTable, mode: Mode, weights: np.ndarray, seeds: Sequence[int],
                   points: int, rng: np.random.Generator, desc: str | None = None) -> list[dict]:
    """Per seed, choice point and allowed option: the return of the episode in which that option
    is begun at that point, minus the prior's (``weights``: the scoring mode's multipliers)."""
    space = OptionSpace(env.config, env.shield, env.planner)
    prior = table.best_option(space, mode.weights)
    rows = []
    for seed in tqdm(seeds, desc=desc, unit='seed', disable=desc is None):
        masks: list[np.ndarray] = []
        play_episode(env, PriorDriver(table, space, mode, explore=lambda mask: masks.append(mask.copy())), seed)
        base = scalar(env.episode_log.reward_vector, weights)
        for point in sorted(rng.choice(len(masks), size=min(points, len(masks)), replace=False).tolist()):
            for option in np.flatnonzero(masks[point]).tolist():
                begun = count()   # the choices of this episode, in order (after the point it may make more)
                driver = PriorDriver(table, space, mode,
                                     explore=lambda mask, p=point, o=option: o if next(begun) == p else None)
                play_episode(env, driver, seed)
                chosen = space.options[option]
                rows.append({'seed': seed, 'point': point, 'choices': len(masks), 'option': option,
                             'lane_intent': chosen.lane_intent, 'style': chosen.style, 'prior': option == prior,
                             'gain': float(scalar(env.episode_log.reward_vector, weights) - base)})
    return rows


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
