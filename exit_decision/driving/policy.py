"""A learned policy as a driver: on the grid, each decision is the shield's greedy choice of the
policy's Q values for its mode; over options, the CAVs whose option ended begin the allowed
option of highest Q value (the forward pass runs only when one does), and the low level makes
the commands (``fixed.OptionDriver``). Training drives the network it learns through the same
driver, with ``explore`` (epsilon-greedy) around the greedy choice.

The mode is bound with ``set_mode`` (a ``model.modes.Mode``): a conditioned policy takes its
weights, a per-mode policy accepts only its own mode (PolicyError for another), and every
option held ends.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Protocol

import numpy as np

from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.options import OptionSpace
from exit_decision.agents.shield import Decision, Shield
from exit_decision.config import ProjectConfig
from exit_decision.driving.anchored import AnchoredSource
from exit_decision.driving.fixed import GridDriver, OptionChooser, OptionDriver
from exit_decision.driving.interface import StepDecision
from exit_decision.errors import PolicyError
from exit_decision.graph import FEATURE_SETS, TrafficGraph
from exit_decision.model.modes import Mode, ModeWeights
from exit_decision.model.names import Planned
from exit_decision.model.policy import PolicyController, greedy_decision, load_controllers
from exit_decision.traffic import TrafficSnapshot, VehicleState

#: training's exploration: given a CAV's mask, an action (or option) to take instead of the
#: greedy one, or None to stay greedy
Explore = Callable[[np.ndarray], int | None]


class QSource(Protocol):
    """What a policy driver chooses with: a loaded policy (``model.policy.PolicyController``) or
    the network a training run learns (``learning.collecting``)."""
    name: str
    shield: Shield
    planner: LanePlanner | None

    def network_weights(self, mode: Mode) -> np.ndarray | None: ...

    def q_values(self, graph: TrafficGraph, snapshot: TrafficSnapshot,
                 network_weights: np.ndarray | None) -> np.ndarray: ...


class PolicyDriver:
    """A Q source driving the CAVs for its mode, on the grid (``options`` None) or over options."""

    def __init__(self, source: QSource, options: OptionSpace | None, mode: Mode | None = None,
                 explore: Explore | None = None):
        self.source, self.name, self.explore = source, source.name, explore
        self.mode: Mode | None = None
        self._network_weights: np.ndarray | None = None
        self._driver = GridDriver(self.name, source.shield.grid, self.grid_decision) if options is None else \
            OptionDriver(self.name, options, self._option_chooser)
        if mode is not None:
            self.set_mode(mode)

    def set_mode(self, mode: Mode) -> None:
        self._network_weights = self.source.network_weights(mode)   # refused here, not at a decision
        self.mode = mode
        self.reset()

    def reset(self) -> None:
        self._driver.reset()

    def decide(self, graph: TrafficGraph, snapshot: TrafficSnapshot, time: float) -> StepDecision:
        if self.mode is None:
            raise PolicyError(f'{self.name}: no mode set (set_mode) before the first decision')
        return self._driver.decide(graph, snapshot, time)

    def grid_decision(self, graph: TrafficGraph, snapshot: TrafficSnapshot) -> Decision:
        """On the grid: the shield's decision of the greedy (or exploring) choice."""
        q = self.source.q_values(graph, snapshot, self._network_weights)
        return greedy_decision(self.source.shield, graph, snapshot, q, explore=self.explore, planner=self.source.planner)

    def _option_chooser(self, graph: TrafficGraph, snapshot: TrafficSnapshot) -> OptionChooser:
        """The chooser of one decision: exploration first (training), else the allowed option of
        highest Q value; the forward pass runs at the first greedy choice, so a decision at which
        every CAV holds its option costs none."""
        first: dict = {}

        def choose(vehicle: VehicleState, mask: np.ndarray) -> int:
            if self.explore is not None:
                explored = self.explore(mask)
                if explored is not None:
                    return explored
            if not first:
                first.update(q=self.source.q_values(graph, snapshot, self._network_weights), row_of=graph.row_of())
            return int(np.where(mask, first['q'][first['row_of'][vehicle.vehicle_id]], -np.inf).argmax())
        return choose


def policy_driver(controller: PolicyController, config: ProjectConfig, mode: Mode | None = None) -> PolicyDriver:
    """The driver of a loaded policy, over the config's options when the policy acts on them
    (an anchored policy through its departure scores, ``anchored``)."""
    options = OptionSpace(config, controller.shield, controller.planner) \
        if controller.policy.action_space == 'options' else None
    source = AnchoredSource(controller, options) if 'anchor' in controller.policy.metadata else controller
    return PolicyDriver(source, options, mode)


def own_mode(controller: PolicyController, modes: ModeWeights, mode: str) -> Mode:
    """The mode a policy drives when scored under ``mode``: that mode for a conditioned policy,
    its own for a per-mode one."""
    return modes.mode(mode if controller.policy.conditioned else controller.policy.mode)


def load_drivers(config: ProjectConfig, policy_dir: Path, planned_policies: Iterable[Planned], shield: Shield,
                 start: Mode) -> dict[Planned, PolicyDriver]:
    """The drivers of the planned policies (``policy.load_controllers``, with the config's lane
    planner), each in its mode (a per-mode policy its own, a conditioned one ``start``) and each
    network run once on an empty graph: the first forward pass is slow, and should not be the
    first decision's. PolicyError, naming the file, as ``load_controllers``."""
    controllers = load_controllers(config, policy_dir, planned_policies, shield, LanePlanner.of(config, shield))
    n, f = config.graph.max_vehicles, len(FEATURE_SETS[config.graph.feature_set])
    idle = TrafficGraph(np.zeros((n, f), np.float32), np.zeros((n, n), np.uint8), np.zeros(n, bool), ('',) * n)
    modes, drivers = ModeWeights(config), {}
    for key, controller in controllers.items():
        driver = policy_driver(controller, config, start if controller.policy.conditioned else modes.mode(key[1]))
        controller.q_values(idle, TrafficSnapshot([]), controller.network_weights(driver.mode))
        drivers[key] = driver
    return drivers
