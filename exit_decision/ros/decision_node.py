"""decision_node: the trained policy of the active mode drives every CAV.

At start it loads one checkpoint per (algorithm, mode) for the modes of parameter ``modes``
from ``policy_dir/<algorithm>_<mode>/policy.pt``; a missing, corrupt or incompatible file
stops the node at start, naming the path. On each decision step it pairs the graph with the
vehicle states of the same step (the shield needs gaps and lanes), runs the greedy policy
under the same shield as training and evaluation, and publishes the commands stamped with
mode, algorithm and policy file. ``mode`` and ``algorithm`` switch at runtime through the
standard parameter service: a value without a loaded policy is refused with the reason; an
accepted one is used from the next graph. Diagnostics count decisions, shield overrides of
the network's first choice, and rejected messages (malformed, wrong size, stale).
"""
from __future__ import annotations

from pathlib import Path

from exit_decision_msgs.msg import CavCommandArray, TrafficGraph, VehicleStateArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from exit_decision.actions import ActionGrid
from exit_decision.agents.shield import Shield
from exit_decision.errors import PolicyError
from exit_decision.graph import FEATURE_SETS
from exit_decision.policy import PolicyController, load_policy
from exit_decision.ros.common import (COMMANDS_TOPIC, GRAPH_TOPIC, STATES_TOPIC, STREAM_QOS, Diagnostics,
                                      declare_config, describe, run_node)
from exit_decision.ros.conversions import MessageError, commands_to_msg, graph_from_msg, states_from_msg
from exit_decision.scenario.geometry import RoadGeometry

ALGORITHMS = ('gqn', 'mdgqn')
PAIRING_WINDOW = 20   # steps of unpaired graphs / states kept while waiting for the other half


def default_policy_dir() -> Path:
    """The repository's policies/ when run from a checkout, else the installed share dir."""
    from exit_decision.config import default_config_dir
    return default_config_dir().parent / 'policies'


class DecisionNode(Node):
    def __init__(self):
        super().__init__('decision_node')
        config = declare_config(self)
        p = self.declare_parameter
        policy_dir = Path(p('policy_dir', '', describe(
            'directory with <algorithm>_<mode>/policy.pt; empty: the shipped policies', read_only=True)).value
            or default_policy_dir())
        modes = list(p('modes', ['AGGI', 'AGGP', 'CONI', 'CONP'], describe(
            'modes whose policies are loaded at start', read_only=True)).value)
        algorithms = list(p('algorithms', list(ALGORITHMS), describe(
            'algorithms whose policies are loaded at start', read_only=True)).value)
        self.grid = ActionGrid(config.env.actions)
        self.shield = Shield.of(config, self.grid, RoadGeometry.of(config.scenario.road))
        self.controllers: dict[tuple[str, str], PolicyController] = {}
        for algorithm in algorithms:
            for mode in modes:
                config.mode(mode)
                policy = load_policy(policy_dir / f'{algorithm}_{mode}' / 'policy.pt')
                policy.check_compatible(config.graph.max_vehicles, config.graph.feature_set,
                                        config.env.decision_interval, self.grid)
                self.controllers[(algorithm, mode)] = PolicyController(policy, self.shield)
        self.mode = p('mode', modes[0], describe('decision mode', constraints=' | '.join(modes))).value
        self.algorithm = p('algorithm', algorithms[-1], describe(
            'gqn or mdgqn', constraints=' | '.join(algorithms))).value
        if (self.algorithm, self.mode) not in self.controllers:
            raise PolicyError(f'no policy loaded for algorithm={self.algorithm!r}, mode={self.mode!r}')
        self.interval = config.env.decision_interval
        self.num_nodes = config.graph.max_vehicles
        self.num_features = len(FEATURE_SETS[config.graph.feature_set])
        self.add_on_set_parameters_callback(self.validate_parameters)
        self.add_post_set_parameters_callback(self.apply_parameters)
        self.graphs: dict[tuple[int, int], TrafficGraph] = {}
        self.states: dict[tuple[int, int], VehicleStateArray] = {}
        self.last_decided: tuple[int, int] = (-1, -1)
        self.publisher = self.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
        self.create_subscription(TrafficGraph, GRAPH_TOPIC, self.on_graph, STREAM_QOS)
        self.create_subscription(VehicleStateArray, STATES_TOPIC, self.on_states, STREAM_QOS)
        self.diagnostics = Diagnostics(self, 'decision_node')
        self.get_logger().info(f'loaded {len(self.controllers)} policies from {policy_dir}; '
                               f'active: {self.algorithm}/{self.mode}')

    # --- parameters -------------------------------------------------------------------------

    def validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse a mode or algorithm without a loaded policy (other parameters: not ours)."""
        chosen = {'mode': self.mode, 'algorithm': self.algorithm}
        chosen.update({p.name: p.value for p in parameters if p.name in chosen})
        loaded = {'algorithm': sorted({a for a, _ in self.controllers}),
                  'mode': sorted({m for _, m in self.controllers})}
        for name, value in chosen.items():
            if value not in loaded[name]:
                return SetParametersResult(successful=False, reason=(
                    f'unknown {name} {value!r}: no policy loaded for it; loaded {name}s: '
                    f'{", ".join(loaded[name])}'))
        return SetParametersResult(successful=True)

    def apply_parameters(self, parameters: list[Parameter]) -> None:
        for parameter in parameters:
            if parameter.name in ('mode', 'algorithm'):
                setattr(self, parameter.name, parameter.value)
                self.get_logger().info(f'active policy now {self.algorithm}/{self.mode}')

    # --- messages ---------------------------------------------------------------------------

    def on_states(self, msg: VehicleStateArray) -> None:
        if msg.step % self.interval == 0:
            self.states[(msg.episode, msg.step)] = msg
            self.try_decide((msg.episode, msg.step))

    def on_graph(self, msg: TrafficGraph) -> None:
        key = (msg.episode, msg.step)
        if msg.step % self.interval:
            return
        if key <= self.last_decided:
            self.diagnostics.count('rejected_stale_graphs')
            self.get_logger().warning(f'graph of episode {key[0]} step {key[1]} arrived after a later one',
                                      throttle_duration_sec=5.0)
            return
        self.graphs[key] = msg
        self.try_decide(key)

    def try_decide(self, key: tuple[int, int]) -> None:
        if key not in self.graphs or key not in self.states:
            self.forget_before((key[0], key[1] - PAIRING_WINDOW * self.interval))
            return
        graph_msg, states_msg = self.graphs.pop(key), self.states.pop(key)
        self.forget_before(key)
        self.last_decided = key
        try:
            graph = graph_from_msg(graph_msg, expected_nodes=self.num_nodes, expected_features=self.num_features)
            vehicles = states_from_msg(states_msg)
            controller = self.controllers[(self.algorithm, self.mode)]
            decision = controller.decide(graph, vehicles)
        except (MessageError, KeyError) as error:   # KeyError: a CAV of the graph is not in the states
            self.diagnostics.count('rejected_graphs')
            self.get_logger().warning(f'rejected graph of step {key[1]}: {error}', throttle_duration_sec=5.0)
            return
        commands = {vehicle_id: self.grid.command(index) for vehicle_id, index in decision.actions.items()}
        self.publisher.publish(commands_to_msg(commands, episode=key[0], step=key[1], stamp=graph_msg.header.stamp,
                                               mode=self.mode, algorithm=self.algorithm,
                                               policy=str(controller.policy.path)))
        self.diagnostics.count('decisions', len(commands))
        self.diagnostics.count('shield_overrides', decision.overridden)

    def forget_before(self, key: tuple[int, int]) -> None:
        for store in (self.graphs, self.states):
            for old in [k for k in store if k < key]:
                if store is self.graphs:
                    self.diagnostics.count('rejected_unpaired_graphs')
                del store[old]


def main() -> int:
    return run_node('decision_node', DecisionNode)


if __name__ == '__main__':
    raise SystemExit(main())
