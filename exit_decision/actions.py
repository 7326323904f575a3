"""The discrete joint action of one CAV: (lane change) x (acceleration) (paper 000, Section 2.3).

Index = lane_change_index * len(accelerations) + acceleration_index. The default grid is
{right, keep, left} x [-8, 5] m/s^2 at 0.5 m/s^2 = 3 x 27 = 81 actions.
"""
from __future__ import annotations

import numpy as np

from exit_decision.config import ActionGridConfig
from exit_decision.traffic import CavCommand

#: the action of a graph row that did not act (no CAV in it, or one not deciding)
NO_ACTION = -1


class ActionGrid:
    def __init__(self, config: ActionGridConfig):
        self.lane_changes = tuple(config.lane_changes)
        count = int(round((config.acceleration_max - config.acceleration_min) / config.acceleration_step)) + 1
        self.accelerations = np.round(config.acceleration_min + config.acceleration_step * np.arange(count), 6)
        self.size = len(self.lane_changes) * len(self.accelerations)
        #: lane change and acceleration of every action index
        self.lane_change_of = np.repeat(np.array(self.lane_changes), len(self.accelerations))
        self.acceleration_of = np.tile(self.accelerations, len(self.lane_changes))
        # lane change -> (size,) bool, the actions that make it (read-only: shared by every mask)
        self._rows = {change: self.lane_change_of == change for change in (-1, 0, 1)}
        for rows in self._rows.values():
            rows.flags.writeable = False

    def rows(self, lane_change: int) -> np.ndarray:
        """(size,) bool, read-only: the actions with this lane change (none for one the grid
        lacks), made once for every mask."""
        return self._rows[lane_change]

    def index(self, lane_change: int, acceleration: float) -> int:
        """The action closest to the given lane change and acceleration."""
        if lane_change not in self.lane_changes:
            raise ValueError(f'lane change {lane_change} is not in the grid {self.lane_changes}')
        a = int(np.argmin(np.abs(self.accelerations - acceleration)))
        return self.lane_changes.index(lane_change) * len(self.accelerations) + a

    def command(self, index: int) -> CavCommand:
        if not 0 <= index < self.size:
            raise ValueError(f'action {index} is outside the grid of {self.size} actions')
        return CavCommand(int(self.lane_change_of[index]), float(self.acceleration_of[index]))
