"""Paired comparisons over seeds: the mean difference and its 95% confidence interval."""
from __future__ import annotations

from collections.abc import Sequence

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
