"""Paired comparisons over seeds: the mean difference and its 95% confidence interval, and the
one pairing of two runs' episodes by seed (checked: the same seeds on both sides)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

Z_95 = 1.959964   # normal quantile: with >= 30 seeds the t quantile is within 4% of it


def paired_interval(differences: Sequence[float]) -> tuple[float, float, float]:
    """(mean, low, high) of per-seed differences: mean -+ 1.96 standard errors."""
    values = np.asarray(differences, dtype=float)
    mean = float(values.mean())
    if values.size < 2:
        return mean, float('nan'), float('nan')
    half = Z_95 * float(values.std(ddof=1)) / np.sqrt(values.size)
    return mean, mean - half, mean + half


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
