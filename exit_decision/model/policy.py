"""Policy checkpoints and greedy inference, used by evaluation, replay and the decision node.

A checkpoint is self-describing: the network's state_dict plus plain-data metadata (network
shape, state encoder, action grid, action space, decision interval, feature set, N, mode,
algorithm (the method's name), seed, git revision, training summary), so it loads with
``torch.load(weights_only=True)`` and rebuilds its own network and encoder (a checkpoint
without one reads the graph as built; one without an action space acts on the grid).
``GraphPolicy.q_values`` encodes the graph and the vehicle states for its method and runs all
rows in one forward pass; ``greedy_decision`` chooses, per CAV, the best action the shield
allows (the lane planner, when configured, driving the CAVs that are off their route), and
``PolicyController`` holds a policy with the shield and planner it drives under (the drivers
of ``driving.policy`` choose with them). Checkpoints are written by training
(``learning.checkpoints``). ``load_controller`` and
``load_controllers`` load and check the policies of a configuration, by file or by (algorithm,
mode) (``names``), for every caller alike.
"""
from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from exit_decision.actions import ActionGrid
from exit_decision.agents.lane_planner import LanePlanner
from exit_decision.agents.shield import Decision, Shield
from exit_decision.config import ActionGridConfig, ConfigError, ProjectConfig
from exit_decision.encoders import StateEncoder
from exit_decision.errors import PolicyError
from exit_decision.graph import TrafficGraph
from exit_decision.model.modes import Mode
from exit_decision.model.names import Planned, action_space_of, algorithm_name, is_conditioned, policy_path, run_name
from exit_decision.model.networks import GraphQNetwork, NetworkShape
from exit_decision.traffic import TrafficSnapshot, VehicleState

CHECKPOINT_FORMAT = 'exit_decision.policy/1'
#: the action spaces a checkpoint's metadata may name (``action_space``; a checkpoint without it: 'grid')
ACTION_SPACES = ('grid', 'options')


def q_values(network: GraphQNetwork, graph: TrafficGraph, weights: np.ndarray | None = None) -> np.ndarray:
    """(N, A) Q values of every row of one graph in one forward pass (rows that are not
    CAVs are computed but meaningless); ``weights``: the mode's six weights, for a
    mode-conditioned network."""
    return network.one_graph(graph.features, graph.adjacency, weights)


class GraphPolicy:
    """A checkpoint's network (or, for a policy anchored on its prior, ``driving.anchored``, its
    ensemble's ``members``: the first is ``network``) with its metadata."""

    def __init__(self, path: Path, network: GraphQNetwork, metadata: dict[str, Any],
                 members: tuple[GraphQNetwork, ...] = ()):
        self.path = path
        self.network = network.eval()
        self.members = (self.network, *(member.eval() for member in members))
        self.metadata = metadata
        self.action_space = metadata.get('action_space', 'grid')
        self.grid = ActionGrid(ActionGridConfig(**metadata['action_grid']))
        self.encoder = StateEncoder(**metadata.get('encoder', {'name': 'graph', 'graph_features': network.shape.num_features,
                                                              'lane_count': 3, 'speed_limit': 1.0}))

    @property
    def label(self) -> str:
        return f'{self.metadata.get("algorithm", "?")}/{self.metadata.get("mode", "?")}'

    def check_compatible(self, config: ProjectConfig) -> None:
        """Raise PolicyError when the policy was trained for other graphs or actions than ``config``'s."""
        expected = {'num_nodes': config.graph.max_vehicles, 'feature_set': config.graph.feature_set,
                    'decision_interval': config.env.decision_interval}
        for key, value in expected.items():
            if self.metadata.get(key) != value:
                raise PolicyError(f'{self.path}: trained with {key}={self.metadata.get(key)!r}, '
                                  f'the configuration has {value!r}')
        grid = ActionGrid(config.env.actions)
        if grid.size != self.grid.size or not np.allclose(grid.accelerations, self.grid.accelerations):
            raise PolicyError(f'{self.path}: its action grid differs from the configured one')
        if self.action_space == 'options' and self.metadata.get('options') != config.env.options.model_dump():
            raise PolicyError(f'{self.path}: trained over other options than config/env.yaml\'s `options`')

    @property
    def conditioned(self) -> bool:
        """One network for every mode: Q(s, a, w) takes the mode's weights."""
        return self.network.conditioned

    @property
    def mode(self) -> str | None:
        """The mode a per-mode policy was trained for; None for a conditioned one."""
        return None if self.conditioned else self.metadata.get('mode')

    @property
    def run_name(self) -> str:
        """The name of its training run by the naming rule (``model.names``): ``<method>[_options]_<mode>``
        or ``<method>[_options]_conditioned``."""
        return run_name(algorithm_name(self.metadata['algorithm'], self.action_space, self.conditioned),
                        self.metadata['mode'])

    @property
    def prior(self) -> dict | None:
        """The prior table a policy over options was trained beside (``driving.prior.PriorTable``'s
        metadata: each fixed style's mean reward vector on the validation seeds); None before it."""
        return self.metadata.get('prior')

    @property
    def measures(self) -> bool:
        """Trained with our measures (shield, lane planner, demonstrations); False: a method
        run as published, which drives with only the lanes that exist masked."""
        return self.metadata.get('measures', True)

    def q_values(self, graph: TrafficGraph, snapshot: TrafficSnapshot,
                 weights: np.ndarray | None = None) -> np.ndarray:
        """(N, A) Q values of the graph's rows, as this policy's method sees the traffic;
        ``weights``: the mode's, for a conditioned policy (``PolicyController`` checks them)."""
        return q_values(self.network, self.encoder.encode(graph, snapshot), weights)

    def member_q_values(self, graph: TrafficGraph, snapshot: TrafficSnapshot,
                        weights: np.ndarray | None = None) -> np.ndarray:
        """(K, N, A) every member's Q values (the graph encoded once)."""
        encoded = self.encoder.encode(graph, snapshot)
        return np.stack([q_values(member, encoded, weights) for member in self.members])


def load_policy(path: Path | str) -> GraphPolicy:
    """The checkpoint at ``path``; PolicyError, naming the path, for one that is missing,
    unreadable or not a policy."""
    path = Path(path)
    if not path.is_file():
        raise PolicyError(f'{path}: no such policy file')
    try:
        data = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as error:  # torch raises many types for a damaged file
        raise PolicyError(f'{path}: not a readable policy checkpoint ({type(error).__name__}: {error})') from None
    if not isinstance(data, dict) or data.get('format') != CHECKPOINT_FORMAT:
        raise PolicyError(f'{path}: not an {CHECKPOINT_FORMAT} checkpoint')
    action_space = data.get('metadata', {}).get('action_space', 'grid')
    if action_space not in ACTION_SPACES:
        raise PolicyError(f'{path}: action space {action_space!r} is not known; known: {", ".join(ACTION_SPACES)}')
    try:
        networks = []
        for state_dict in (data['state_dict'], *data.get('members', ())):
            networks.append(GraphQNetwork(NetworkShape(**data['network'])))
            networks[-1].load_state_dict(state_dict)
        return GraphPolicy(path, networks[0], data['metadata'], tuple(networks[1:]))
    except (KeyError, TypeError, ValueError, RuntimeError, ConfigError) as error:
        raise PolicyError(f'{path}: checkpoint content does not fit ({error})') from None


def greedy_decision(shield: Shield, graph: TrafficGraph, snapshot: TrafficSnapshot, q: np.ndarray,
                    explore: Callable[[np.ndarray], int] | None = None,
                    planner: LanePlanner | None = None) -> Decision:
    """Each CAV row's best allowed action by its Q values, under the shield (front to back);
    ``explore``: called with the mask for a CAV that explores instead (returns an action or
    None to stay greedy); ``planner``: drives CAVs off their route and keeps the others on it."""
    row_of = graph.row_of()

    def choose(vehicle: VehicleState, mask: np.ndarray) -> int:
        chosen = planner.choose(vehicle, mask, snapshot) if planner is not None else None
        if chosen is None and explore is not None:
            chosen = explore(mask)
        if chosen is not None:
            return chosen
        return int(np.where(mask, q[row_of[vehicle.vehicle_id]], -np.inf).argmax())
    return shield.decide(snapshot, graph.cav_ids(), choose,
                         preferred=lambda vehicle: int(q[row_of[vehicle.vehicle_id]].argmax()),
                         restrict=planner.restrict if planner is not None else None)


class PolicyController:
    """A loaded policy with what it chooses under: the shield, and the lane planner for a policy
    trained with our measures (one trained as published drives as it was trained: the bare
    shield, no planner). ``driving.policy.PolicyDriver`` drives with it."""

    def __init__(self, policy: GraphPolicy, shield: Shield, planner: LanePlanner | None = None):
        torch.set_num_threads(1)   # one small forward per decision: threads only add contention
        self.policy = policy
        self.shield = shield if policy.measures else shield.bare()
        self.planner = planner if policy.measures else None
        self.name = policy.label

    def network_weights(self, mode: Mode) -> np.ndarray | None:
        """What the network takes to decide in ``mode``: a conditioned policy the mode's weights,
        a per-mode one nothing; PolicyError, in one line, for a per-mode policy given another mode."""
        if self.policy.conditioned:
            return mode.weights
        if mode.name != self.policy.mode:
            raise PolicyError(f'{self.policy.path}: a policy of mode {self.policy.mode!r} decides for that mode '
                              f'only, not for mode {mode.name!r} (weights {mode.weights.tolist()}); a '
                              f'mode-conditioned policy decides for any')
        return None

    def q_values(self, graph: TrafficGraph, snapshot: TrafficSnapshot, network_weights: np.ndarray | None) -> np.ndarray:
        """(N, A) Q values of the graph's rows (``network_weights``: from ``network_weights``)."""
        return self.policy.q_values(graph, snapshot, network_weights)


def load_controller(config: ProjectConfig, path: Path | str, shield: Shield, planner: LanePlanner | None = None,
                    planned: Planned | None = None, action_spaces: tuple[str, ...] = ('grid',)) -> PolicyController:
    """The policy at ``path``, checked against ``config`` (graph, decision interval, action grid)
    and, for a ``planned`` (algorithm, mode), against that: conditioned as the algorithm's name
    says, or trained for that mode; ready to decide under ``shield`` (and ``planner``).
    PolicyError, naming the path, for a policy that is missing, unreadable or does not fit, or
    acts in an action space not in ``action_spaces``."""
    policy = load_policy(path)
    policy.check_compatible(config)
    if policy.action_space not in action_spaces:
        raise PolicyError(f'{policy.path}: a policy over {policy.action_space}; this command runs policies over '
                          f'{" or ".join(action_spaces)} only')
    if planned is not None:
        algorithm, mode = planned
        if policy.conditioned != is_conditioned(algorithm):
            raise PolicyError(f'{policy.path}: a mode-conditioned policy; algorithm {algorithm!r} needs one per mode'
                              if policy.conditioned else
                              f'{policy.path}: not a mode-conditioned policy, as algorithm {algorithm!r} needs')
        if policy.action_space != action_space_of(algorithm):
            raise PolicyError(f'{policy.path}: a policy over {policy.action_space}; algorithm {algorithm!r} needs one '
                              f'over {action_space_of(algorithm)} (a method over options has _options in its name)')
        if mode is not None and policy.mode != mode:
            raise PolicyError(f'{policy.path}: a policy of mode {policy.mode!r}; algorithm {algorithm!r} at mode '
                              f'{mode!r} needs one of that mode')
    return PolicyController(policy, shield, planner)


def load_controllers(config: ProjectConfig, policy_dir: Path, planned: Iterable[Planned], shield: Shield,
                     planner: LanePlanner | None = None) -> dict[Planned, PolicyController]:
    """The policies of ``planned`` (``names.planned_policies``) from ``policy_dir``
    (``names.policy_path``), each loaded and checked by ``load_controller``, on the grid or
    over options as the algorithm's name says."""
    return {key: load_controller(config, policy_path(policy_dir, *key), shield, planner, key, ACTION_SPACES)
            for key in planned}
