"""Paired comparisons over seeds: the mean difference and its 95% confidence interval, and the
one pairing of two runs' episodes by seed (checked: the same seeds on both sides); the slope of a
learning curve with its 95% interval (has it flattened?)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

Z_95 = 1.959964   # normal quantile: with >= 30 seeds the t quantile is within 4% of it
#: Student's t 0.975 quantiles by degrees of freedom (1-30; beyond, Z_95 is within 4%): a fitted
#: slope has few points
T_95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145,
        2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048,
        2.045, 2.042)


def paired_interval(differences: Sequence[float]) -> tuple[float, float, float]:
    """(mean, low, high) of per-seed differences: mean -+ 1.96 standard errors."""
    return _mean_interval(differences, lambda degrees: Z_95)


def t_interval(values: Sequence[float]) -> tuple[float, float, float]:
    """(mean, low, high) with Student's t quantile: for a few samples (repeated futures of a point)."""
    return _mean_interval(values, _t_95)


def _mean_interval(values: Sequence[float], quantile) -> tuple[float, float, float]:
    """(mean, low, high): mean -+ ``quantile(degrees of freedom)`` standard errors; nan bounds below 2."""
    values = np.asarray(values, dtype=float)
    mean = float(values.mean())
    if values.size < 2:
        return mean, float('nan'), float('nan')
    half = quantile(values.size - 1) * float(values.std(ddof=1)) / np.sqrt(values.size)
    return mean, mean - half, mean + half


def _t_95(degrees: int) -> float:
    return T_95[degrees - 1] if degrees <= len(T_95) else Z_95


def paired_differences(own: Sequence[Mapping], theirs: Sequence[Mapping], metric: str) -> np.ndarray:
    """Per seed, ``own``'s ``metric`` minus ``theirs``' on the same seed (rows with a ``seed``), in
    ``own``'s order; ValueError when the two runs are not on the same seeds."""
    by_seed = {row['seed']: row[metric] for row in theirs}
    seeds = [row['seed'] for row in own]
    if len(set(seeds)) != len(seeds) or set(seeds) != set(by_seed) or len(by_seed) != len(theirs):
        unpaired = sorted(set(seeds) ^ set(by_seed), key=str)
        raise ValueError(f'runs paired by seed are on other seeds (unpaired: {unpaired[:5]}'
                         f'{" ..." if len(unpaired) > 5 else ""}, or a seed twice)')
    return np.array([float(row[metric]) - float(by_seed[row['seed']]) for row in own])


def paired_difference(own: Sequence[Mapping], theirs: Sequence[Mapping], metric: str) -> tuple[float, float, float]:
    """(mean, low, high) of ``paired_differences``."""
    return paired_interval(paired_differences(own, theirs, metric))


def slope_interval(x: Sequence[float], y: Sequence[float]) -> tuple[float, float, float]:
    """(slope, low, high): the least-squares line's slope of ``y`` on ``x`` and its 95% interval
    (t with n - 2 degrees of freedom); nan bounds below 3 points."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    slope, intercept = np.polyfit(x, y, 1)
    if x.size < 3:
        return float(slope), float('nan'), float('nan')
    residuals = y - (slope * x + intercept)
    error = np.sqrt(residuals @ residuals / (x.size - 2) / ((x - x.mean()) @ (x - x.mean())))
    half = _t_95(x.size - 2) * error
    return float(slope), float(slope - half), float(slope + half)


#: a learning curve has flattened when its last third holds this many validations at least and
#: the slope's interval there reaches 0 or below (issue 39, item 3)
MIN_LAST_THIRD_VALIDATIONS = 6


def last_third_slopes(rows: Sequence[Mapping], metric: str = 'gain') -> dict[str, dict[str, float]]:
    """Per mode of validation rows (``episode``, ``mode``, ``metric``): the slope per episode of
    ``metric`` over the last third of the episodes validated, its interval, the validations there
    and whether the curve has flattened."""
    out = {}
    for mode in dict.fromkeys(row['mode'] for row in rows):
        points = sorted((int(row['episode']), float(row[metric])) for row in rows if row['mode'] == mode)
        start = points[-1][0] * 2 / 3
        last = [(x, y) for x, y in points if x >= start]
        slope, low, high = slope_interval(*zip(*last)) if len(last) >= 2 else (float('nan'),) * 3
        out[mode] = {'from_episode': last[0][0], 'validations': len(last), 'slope': slope, 'low': low, 'high': high,
                     'flat': len(last) >= MIN_LAST_THIRD_VALIDATIONS and low <= 0.0}
    return out
