"""Summaries of episode metrics (``exit_decision.episode_log``) over many episodes."""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from exit_decision.episode_log import METRICS


def summarize(episodes: Sequence[dict[str, float]]) -> dict[str, tuple[float, float]]:
    """Mean and standard deviation of each metric over episodes (NaNs ignored; a metric the
    episodes do not carry, as the stack's episode events lack the CAV-only ones: NaN)."""
    table = {}
    for name in METRICS:
        values = np.array([e.get(name, np.nan) for e in episodes], dtype=float)
        finite = values[np.isfinite(values)]
        table[name] = (float(finite.mean()), float(finite.std())) if finite.size else (np.nan, np.nan)
    return table


def markdown_table(rows: Iterable[tuple[str, dict[str, tuple[float, float]]]]) -> str:
    """One line per (label, summary): mean ± std of every metric some row has (a metric no row
    measured, such as the CAVs' headway in the stack's episode events, is left out)."""
    rows = list(rows)
    metrics = [m for m in METRICS if any(not math.isnan(summary[m][0]) for _, summary in rows)]
    lines = ['| run | ' + ' | '.join(metrics) + ' |', '|---' * (len(metrics) + 1) + '|']
    for label, summary in rows:
        cells = [f'{mean:.4g} ± {std:.2g}' for mean, std in (summary[m] for m in metrics)]
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)
