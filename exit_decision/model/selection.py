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
from exit_decision.model.modes import CUSTOM_MODE, Mode, ModeWeights, check_weights
from exit_decision.model.names import Planned, planned

#: the parameters a selection is made of
SELECTION_PARAMETERS = ('mode', 'algorithm', 'reward_weights')


class PolicySelection:
    """The active algorithm and ``Mode`` among the ``planned`` policies of a config.

    A parameter set is resolved once, when ``completed`` adds the counterpart of a mode or
    weights set alone (the mode's name is converted to weights there, and only there);
    ``problem`` and ``apply`` of the same changes reuse that resolution."""

    def __init__(self, config: ProjectConfig, planned_policies: Sequence[Planned], algorithm: str, mode: str,
                 weights: Sequence[float]):
        """PolicyError, in one line, when the start values cannot drive; weights given at
        start name the mode (the returned ``mode`` may differ from ``mode``)."""
        self.config, self.planned = config, list(planned_policies)
        self.modes = ModeWeights(config)
        for _, planned_mode in self.planned:
            if planned_mode is not None and planned_mode not in self.modes:
                config.mode(planned_mode)   # an unknown one fails now (ConfigError), not after loading
        if not isinstance(mode, str) or mode not in config.modes and mode != CUSTOM_MODE:
            raise PolicyError(f'parameter mode: {mode!r} is not allowed; allowed: {" | ".join(config.modes)}')
        reason = check_weights(weights)
        if reason:
            raise PolicyError(f'reward_weights {list(weights)}: {reason}')
        self.algorithm, self.mode = algorithm, self.modes.of_weights(weights)
        self._resolved: tuple[tuple, Resolution] | None = None   # the last changes resolved, and how
        resolution = self._resolve({})
        if isinstance(resolution, str):
            raise PolicyError(resolution)

    @property
    def key(self) -> Planned:
        """The planned policy that drives now."""
        return planned(self.algorithm, self.mode.name)

    @property
    def weights(self) -> np.ndarray:
        return self.mode.weights

    def completed(self, changes: dict) -> dict:
        """``changes`` with the counterpart a mode or weights set alone implies (values of the
        wrong type are left for ``problem`` to refuse)."""
        resolution = self._resolution(changes)
        if isinstance(resolution, str) or ('mode' in changes) == ('reward_weights' in changes):
            return changes
        _, mode = resolution
        added = {'reward_weights': mode.weights.tolist()} if 'mode' in changes else {'mode': mode.name}
        completed = {**changes, **added}
        self._resolved = (_key(completed), resolution)
        return completed

    def problem(self, changes: dict) -> str | None:
        """Why the selection with these changes cannot drive (None if it can)."""
        resolution = self._resolution(changes)
        return resolution if isinstance(resolution, str) else None

    def apply(self, changes: dict) -> None:
        """Take accepted changes (the caller ends every held option at any change)."""
        resolution = self._resolution(changes)
        if isinstance(resolution, str):
            raise PolicyError(resolution)
        self.algorithm, self.mode = resolution

    def _resolution(self, changes: dict) -> Resolution:
        key = _key(changes)
        if self._resolved is None or self._resolved[0] != key:
            self._resolved = (key, self._resolve(changes))
        return self._resolved[1]

    def _resolve(self, changes: dict) -> Resolution:
        """(algorithm, Mode) of the selection with ``changes``, or why it cannot drive."""
        algorithm, name = changes.get('algorithm', self.algorithm), changes.get('mode', self.mode.name)
        if not isinstance(name, str) or not isinstance(algorithm, str):
            return f'mode and algorithm are strings, got mode {name!r}, algorithm {algorithm!r}'
        mode = self._mode(changes)
        if isinstance(mode, str):
            return mode
        algorithms = sorted({a for a, _ in self.planned})
        if algorithm not in algorithms:
            return f'unknown algorithm {algorithm!r}: no policy loaded for it; loaded algorithms: {", ".join(algorithms)}'
        if (algorithm, None) in self.planned:
            return algorithm, mode
        loaded = sorted(m for a, m in self.planned if a == algorithm)
        if mode.name not in loaded:
            return (f'unknown mode {mode.name!r}: no policy loaded for it with algorithm {algorithm!r}; loaded modes: '
                    f'{", ".join(loaded)}' + ('' if mode.name != CUSTOM_MODE else
                                             ' (reward_weights off a mode need a conditioned algorithm)'))
        return algorithm, mode

    def _mode(self, changes: dict) -> Mode | str:
        """The ``Mode`` a change of mode and/or weights selects, or why it is refused."""
        name = changes.get('mode')
        if 'reward_weights' in changes:
            weights = changes['reward_weights']
            reason = check_weights(weights)
            if reason:
                return f'reward_weights {weights!r}: {reason}'
            mode = self.modes.of_weights(weights)
            if 'mode' in changes and name != mode.name:
                if name in self.modes or name == CUSTOM_MODE:
                    return (f'mode {name!r} and reward_weights {mode.weights.tolist()} disagree: set one of them '
                            f'(the other follows)')
                return f'unknown mode {name!r}; known modes: {", ".join(self.config.modes)}'
            return mode
        if 'mode' in changes:
            if name == CUSTOM_MODE:
                return f'mode {CUSTOM_MODE!r} is set by setting reward_weights to a point that is no configured mode'
            if name not in self.modes:
                return f'unknown mode {name!r}; known modes: {", ".join(self.config.modes)}'
            return self.modes.mode(name)
        return self.mode


#: a selection's (algorithm, Mode), or why it cannot drive
Resolution = tuple[str, Mode] | str


def _key(changes: dict) -> tuple:
    """Changes as a comparable key (parameter values arrive as lists, tuples or arrays)."""
    def value(v):
        if isinstance(v, str) or not hasattr(v, '__iter__'):
            return v
        try:
            return tuple(float(x) for x in v)
        except (TypeError, ValueError):
            return repr(v)
    return tuple(sorted((k, value(v)) for k, v in changes.items()))
