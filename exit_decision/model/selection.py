"""Which loaded policy drives, for which weights: the decision node's parameters ``mode``,
``algorithm`` and ``reward_weights`` kept consistent, free of ROS (and of torch, so the node
answers parameter requests while its policies load).

Setting a mode sets its weights; setting weights sets the mode whose weights they are, or
``custom`` (``modes``). A change is refused, with the reason in one line, when no planned
policy can drive with it: an unknown algorithm or mode, a per-mode algorithm at custom
weights, a mode and weights that disagree.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from exit_decision.config import ProjectConfig
from exit_decision.errors import PolicyError
from exit_decision.model.modes import CUSTOM_MODE, ModeWeights, check_weights
from exit_decision.model.names import Planned, planned

#: the parameters a selection is made of
SELECTION_PARAMETERS = ('mode', 'algorithm', 'reward_weights')


class PolicySelection:
    """The active (algorithm, mode, weights) among the ``planned`` policies of a config."""

    def __init__(self, config: ProjectConfig, planned_policies: Sequence[Planned], algorithm: str, mode: str,
                 weights: Sequence[float]):
        """PolicyError, in one line, when the start values cannot drive; weights given at
        start name the mode (the returned ``mode`` may differ from ``mode``)."""
        self.config, self.planned = config, list(planned_policies)
        self.modes = ModeWeights(config)
        for _, planned_mode in self.planned:
            if planned_mode is not None:
                self.modes.weights(planned_mode)   # an unknown one fails now, not after loading
        if not isinstance(mode, str) or mode not in config.modes and mode != CUSTOM_MODE:
            raise PolicyError(f'parameter mode: {mode!r} is not allowed; allowed: {" | ".join(config.modes)}')
        reason = check_weights(weights)
        if reason:
            raise PolicyError(f'reward_weights {list(weights)}: {reason}')
        self.algorithm, self.weights = algorithm, np.asarray(weights, dtype=float)
        self.mode = self.modes.name(self.weights)
        problem = self.problem({})
        if problem:
            raise PolicyError(problem)

    @property
    def key(self) -> Planned:
        """The planned policy that drives now."""
        return planned(self.algorithm, self.mode)

    def completed(self, changes: dict) -> dict:
        """``changes`` with the counterpart a mode or weights set alone implies (values of the
        wrong type are left for ``problem`` to refuse)."""
        if 'mode' in changes and 'reward_weights' not in changes:
            if isinstance(changes['mode'], str) and changes['mode'] in self.modes:
                return {**changes, 'reward_weights': self.modes.weights(changes['mode']).tolist()}
        elif 'reward_weights' in changes and 'mode' not in changes:
            if check_weights(changes['reward_weights']) is None:
                return {**changes, 'mode': self.modes.name(changes['reward_weights'])}
        return changes

    def problem(self, changes: dict) -> str | None:
        """Why the selection with these changes cannot drive (None if it can)."""
        chosen = {'mode': self.mode, 'algorithm': self.algorithm, 'reward_weights': self.weights, **changes}
        algorithm, mode = chosen['algorithm'], chosen['mode']
        algorithms = sorted({a for a, _ in self.planned})
        if not isinstance(mode, str) or not isinstance(algorithm, str):
            return f'mode and algorithm are strings, got mode {mode!r}, algorithm {algorithm!r}'
        reason = check_weights(chosen['reward_weights'])
        if reason:
            return f'reward_weights {chosen["reward_weights"]!r}: {reason}'
        if algorithm not in algorithms:
            return f'unknown algorithm {algorithm!r}: no policy loaded for it; loaded algorithms: {", ".join(algorithms)}'
        if mode == CUSTOM_MODE and 'reward_weights' not in changes and 'mode' in changes:
            return f'mode {CUSTOM_MODE!r} is set by setting reward_weights to a point that is no configured mode'
        named = self.modes.name(chosen['reward_weights'])
        if mode != named and (mode in self.config.modes or mode == CUSTOM_MODE):
            return (f'mode {mode!r} and reward_weights {np.asarray(chosen["reward_weights"], float).tolist()} '
                    f'disagree: set one of them (the other follows)')
        if (algorithm, None) in self.planned:
            if mode != CUSTOM_MODE and mode not in self.config.modes:
                return f'unknown mode {mode!r}; known modes: {", ".join(self.config.modes)}'
            return None
        loaded = sorted(m for a, m in self.planned if a == algorithm)
        if mode not in loaded:
            return (f'unknown mode {mode!r}: no policy loaded for it with algorithm {algorithm!r}; loaded modes: '
                    f'{", ".join(loaded)}' + ('' if mode != CUSTOM_MODE else
                                             ' (reward_weights off a mode need a conditioned algorithm)'))
        return None

    def apply(self, changes: dict) -> None:
        """Take accepted changes (the caller ends every held option at any change)."""
        if 'algorithm' in changes:
            self.algorithm = changes['algorithm']
        if 'mode' in changes:
            self.mode = changes['mode']
        if 'reward_weights' in changes:
            self.weights = np.asarray(changes['reward_weights'], dtype=float)
