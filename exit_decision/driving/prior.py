"""The prior over options (issue 39): the best fixed driver for any mode, from measured data.

``PriorTable`` holds each fixed style's mean reward vector (4 rows x incentive/punishment,
``exit_decision.reward``) over the validation seeds, under one reward variant, as the constant
options drove them (``exit-decision options-table``). A mode's return is linear in the vector, so
the best fixed style for ANY weights (the four modes, Table A1's points, a user's
``reward_weights``) is an argmax of a dot product, not a per-mode-name table. The table is plain
data: it travels in a checkpoint's metadata and loads with ``weights_only=True``.

``PriorDriver`` drives it: every CAV holds the constant option of the best style for its mode,
chosen again when the mode changes.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from exit_decision.agents.options import OptionSpace
from exit_decision.driving.fixed import OPTION_PREFIX, OptionDriver
from exit_decision.model.modes import Mode
from exit_decision.reward import ROWS, VECTOR_COLUMNS, weights_of_input



@dataclass(frozen=True)
class PriorTable:
    variant: str                      # the reward variant the vectors are scored under
    seeds: tuple[int, ...]            # the seeds the means are over
    vectors: Mapping[str, np.ndarray]  # style -> (4, 2) mean reward vector

    def returns(self, weights: np.ndarray) -> dict[str, float]:
        """Each style's mean return at a weight input (six numbers)."""
        multipliers = weights_of_input(weights)
        return {style: float((vector * multipliers).sum()) for style, vector in self.vectors.items()}

    def best_indices(self, multipliers: np.ndarray) -> np.ndarray:
        """(B,) index into the table's styles of the best one at each of ``multipliers``
        ((B, 4, 2), ``reward.weights_of_input``): the batched ``best_style`` of training's targets."""
        vectors = np.stack(list(self.vectors.values()))
        return np.einsum('srk,brk->bs', vectors, multipliers).argmax(axis=1)

    def option_indices(self, space: OptionSpace) -> np.ndarray:
        """(styles,) each style's constant option (``route``) in ``space``."""
        return np.array([space.index('route', style) for style in self.vectors], dtype=np.int64)

    def best_option(self, space: OptionSpace, weights: np.ndarray) -> int:
        """The prior's option in ``space`` at ``weights``: the best style on the route's lane plan."""
        return space.index('route', self.best_style(weights))

    def best_style(self, weights: np.ndarray) -> str:
        """The style of highest mean return at ``weights`` (the first on a tie, in table order)."""
        returns = self.returns(weights)
        return max(returns, key=returns.get)

    def to_metadata(self) -> dict:
        """Plain data (lists, numbers, strings) for a checkpoint's metadata."""
        return {'variant': self.variant, 'seeds': list(self.seeds),
                'vectors': {style: vector.tolist() for style, vector in self.vectors.items()}}

    @classmethod
    def from_metadata(cls, data: Mapping) -> PriorTable:
        return cls(data['variant'], tuple(data['seeds']),
                   {style: np.asarray(vector, dtype=float).reshape(len(ROWS), 2) for style, vector in data['vectors'].items()})

    @classmethod
    def from_rows(cls, rows: Sequence[Mapping], variant: str, styles: Sequence[str]) -> PriorTable:
        """From the constant-options table's rows (``constant_options.csv``): each style's mean
        vector over the seeds its run has under ``variant``; ValueError when a style is missing
        or the styles are not on the same seeds."""
        by_style: dict[str, list[Mapping]] = {style: [] for style in styles}
        for row in rows:
            style = str(row['run']).removeprefix(OPTION_PREFIX)
            if row['variant'] == variant and str(row['run']).startswith(OPTION_PREFIX) and style in by_style:
                by_style[style].append(row)
        seeds = {style: sorted(int(row['seed']) for row in episodes) for style, episodes in by_style.items()}
        missing = [style for style, found in seeds.items() if not found]
        if missing:
            raise ValueError(f'no episodes of style(s) {", ".join(missing)} under reward variant {variant!r}')
        first = next(iter(seeds.values()))
        if any(found != first for found in seeds.values()):
            raise ValueError('the styles of the table ran on different seeds')
        vectors = {style: np.array([[float(row[column]) for column in VECTOR_COLUMNS] for row in episodes])
                   .mean(axis=0).reshape(len(ROWS), 2) for style, episodes in by_style.items()}
        return cls(variant, tuple(first), vectors)


class PriorDriver(OptionDriver):
    """Every CAV holds the constant option of the table's best style for the mode (made with one);
    with ``explore`` (training, ``exploration.around: prior``) a CAV may begin another instead."""

    def __init__(self, table: PriorTable, space: OptionSpace, mode: Mode, name: str = 'prior',
                 explore: Callable[[np.ndarray], int | None] | None = None):
        super().__init__(name, space, lambda graph, snapshot: self._choose)
        self.table, self.explore = table, explore
        self.set_mode(mode)

    def _choose(self, vehicle, mask: np.ndarray) -> int:
        explored = self.explore(mask) if self.explore is not None else None
        return self._index if explored is None else explored

    def set_mode(self, mode: Mode) -> None:
        self.style = self.table.best_style(mode.weights)
        self._index = self.table.best_option(self.space, mode.weights)
        self.reset()
