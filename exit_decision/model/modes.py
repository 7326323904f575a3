"""The modes as a policy takes them, free of torch: one value, ``Mode`` (a name and its weight
input, the six numbers of ``reward.weight_input``: the decision weights of result, efficiency,
comfort and safety, then incentive and punishment), and the check of six numbers as a mode.

A ``Mode`` is made at the edge only (a parameter set, a recorded mode, a mode to score under,
a training episode's drawn weights), by ``ModeWeights.mode`` (a name: the one conversion of a
name to weights) or ``ModeWeights.of_weights`` (weights: named by the configured mode they
are, else ``custom``), and travels whole from there to the network (``driving``).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

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


@dataclass(frozen=True, eq=False)
class Mode:
    """A mode as one value: its name (a configured mode's, or ``CUSTOM_MODE``) and its weight
    input, checked when it was made (``ModeWeights``)."""
    name: str
    weights: np.ndarray

    def __repr__(self) -> str:
        return f'Mode({self.name!r}, {self.weights.tolist()})'


class ModeWeights:
    """The configured modes: ``mode(name)`` and ``of_weights(weights)`` make a ``Mode``."""

    def __init__(self, config: ProjectConfig):
        self.config = config
        self._weights = {name: weight_input(mode) for name, mode in config.modes.items()}

    def __contains__(self, name: object) -> bool:
        return name in self._weights

    def mode(self, name: str) -> Mode:
        """Mode ``name`` with its weights: the one conversion of a name to weights; ConfigError
        for a name that is no configured mode."""
        return Mode(name, weight_input(self.config.mode(name)))

    def of_weights(self, weights: Sequence[float] | np.ndarray) -> Mode:
        """The mode these weights are: named by the configured mode with them (the first in config
        order), or ``CUSTOM_MODE``; ValueError, with the reason, for six numbers that are no mode."""
        reason = check_weights(weights)
        if reason:
            raise ValueError(reason)
        values = np.asarray(weights, dtype=float)
        name = next((name for name, known in self._weights.items() if same_weights(known, values)), CUSTOM_MODE)
        return Mode(name, values)


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
