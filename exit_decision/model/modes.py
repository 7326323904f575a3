"""The modes as a policy takes them, free of torch: a mode name and its weight input (the six
numbers of ``reward.weight_input``: the decision weights of result, efficiency, comfort and
safety, then incentive and punishment), both ways, and the check of six numbers as a mode.

Names are converted to weights, and weights named, at the edge only (a parameter set, a
recorded mode, a mode to score under); policies decide for weights (``policy.PolicyController``).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from exit_decision.config import ProjectConfig
from exit_decision.reward import WEIGHT_INPUT_SIZE, weight_input

#: the name of weights that are no configured mode's (a conditioned policy decides for any)
CUSTOM_MODE = 'custom'


def same_weights(a: np.ndarray, b: Sequence[float] | np.ndarray) -> bool:
    """The same mode: ``np.allclose(a, b, atol=1e-9)``, without its overhead (a per-mode policy
    checks the weights of every decision)."""
    b = np.asarray(b, dtype=float)
    return a.shape == b.shape and bool((np.abs(a - b) <= 1e-9 + 1e-5 * np.abs(b)).all())


class ModeWeights:
    """The configured modes and their weight inputs, both ways: ``weights(name)`` and
    ``name(weights)`` (``CUSTOM_MODE`` off every mode)."""

    def __init__(self, config: ProjectConfig):
        self.config = config
        self._weights = {name: weight_input(mode) for name, mode in config.modes.items()}

    def __contains__(self, name: object) -> bool:
        return name in self._weights

    def weights(self, name: str) -> np.ndarray:
        """The weight input of mode ``name``; ConfigError for a name that is no configured mode."""
        return weight_input(self.config.mode(name))

    def name(self, weights: Sequence[float] | np.ndarray) -> str:
        """The configured mode with these weights (the first in config order), or ``CUSTOM_MODE``."""
        return next((name for name, known in self._weights.items() if same_weights(known, weights)), CUSTOM_MODE)


def check_weights(weights: Sequence[float]) -> str | None:
    """Why six numbers are not a valid mode (None if they are): four non-negative decision
    weights summing to 1, then non-negative incentive and punishment weights summing to 1."""
    try:
        values = np.asarray(weights, dtype=float)
    except (TypeError, ValueError):
        return f'expected {WEIGHT_INPUT_SIZE} numbers, got {weights!r}'
    if values.shape != (WEIGHT_INPUT_SIZE,):
        return f'expected {WEIGHT_INPUT_SIZE} numbers (result, efficiency, comfort, safety, incentive, ' \
               f'punishment), got {values.size}'
    if not np.isfinite(values).all() or (values < 0).any():
        return 'every weight must be a finite number >= 0'
    if abs(values[:4].sum() - 1.0) > 1e-6:
        return f'the four decision weights must sum to 1, they sum to {values[:4].sum():.6g}'
    if abs(values[4:].sum() - 1.0) > 1e-6:
        return f'incentive + punishment must be 1, they sum to {values[4:].sum():.6g}'
    return None
