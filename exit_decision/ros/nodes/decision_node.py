"""decision_node: the trained policy of the active mode drives every CAV.

It loads the policies of parameters ``algorithms`` x ``modes`` (``model.names``; a missing,
corrupt or incompatible file stops it at start, naming the path) in a thread: the parameter
services answer meanwhile, and it subscribes and offers commands once they are loaded.

``mode``, ``algorithm`` and ``reward_weights`` switch at runtime through the standard parameter
service, resolved once into a ``Mode`` (``model.selection``) that the active policy driver
drives in from the next graph; every option held ends. Each decision pairs the graph with the
states of its step and publishes the commands (stamped with mode, algorithm and policy file),
then the shield's overrides (grid) or the options held (/exit_decision/cav_options).

Composed with the graph builder (``graph_and_decision``), it is handed each step's checked
states and graph; alone, it subscribes to both (``intake``) and takes a message only if it can
follow the current episode and step (from an episode EVENT_STARTED announced) and every field
fits; otherwise it is rejected whole, counted on /diagnostics, and changes nothing."""
from __future__ import annotations

import threading

from exit_decision_msgs.msg import (CavCommandArray, CavOptionArray, EpisodeEvent, ShieldOverrideArray,
                                    TrafficGraph as GraphMsg, VehicleStateArray)
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from exit_decision.actions import ActionGrid
from exit_decision.agents.shield import Shield
from exit_decision.graph import FEATURE_SETS, TrafficGraph
from exit_decision.input_checks import InputError, StateLimits
from exit_decision.model.selection import SELECTION_PARAMETERS
from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import run_node
from exit_decision.ros.intake import Intake
from exit_decision.ros.messages.commands_cdr import encode_commands
from exit_decision.ros.messages.conversions import graph_from_msg, options_to_msg, overrides_to_msg
from exit_decision.ros.parameters import (declare_config, declare_cpu_affinity, declare_policy_selection,
                                          declare_thread_priority)
from exit_decision.ros.step_pairing import StepPairing
from exit_decision.ros.topics import (COMMANDS_QOS, COMMANDS_TOPIC, EPISODE_TOPIC, EVENT_QOS, GRAPH_QOS, GRAPH_TOPIC,
                                      OPTIONS_TOPIC, OVERRIDES_TOPIC, STATES_QOS, STATES_TOPIC)
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import TrafficSnapshot


class DecisionNode(Node):
    """``composed``: the graph builder of the same process calls ``begin_episode`` and ``decide``
    with each decision step's checked states and graph; the node subscribes to neither."""

    def __init__(self, composed: bool = False, context=None):
        super().__init__('decision_node', context=context)
        self.composed = composed
        self.config = config = declare_config(self)
        declare_thread_priority(self)
        declare_cpu_affinity(self)
        self.policy_dir, self.selection = declare_policy_selection(self, config)
        grid = ActionGrid(config.env.actions)
        geometry = RoadGeometry.of(config.scenario.road)
        self.shield, self.limits = Shield.of(config, grid, geometry), StateLimits.of(config, geometry)
        self.interval, self.step_length = config.env.decision_interval, config.scenario.step_length
        self.num_nodes, self.num_features = config.graph.max_vehicles, len(FEATURE_SETS[config.graph.feature_set])
        self.add_pre_set_parameters_callback(self.complete_parameters)
        self.add_on_set_parameters_callback(self.validate_parameters)
        self.add_post_set_parameters_callback(self.apply_parameters)
        self.last_decided: tuple[int, int] = (-1, -1)
        self.diagnostics = Diagnostics(self, 'decision_node')
        self.pairing = StepPairing(config.scenario.max_steps, self.interval, self.diagnostics.count)
        self.drivers: dict = {}       # (algorithm, mode) -> driving.policy.PolicyDriver, once loaded
        self.loaded: dict | Exception | None = None   # what the loading thread hands over (drivers or error)
        self.when_loaded: list = []   # called once the policies are loaded (composed: the graph builder subscribes)
        self.loaded_signal = self.create_guard_condition(self.start_deciding)
        threading.Thread(target=self.load_policies, name='load_policies', daemon=True).start()

    def load_policies(self) -> None:
        """(Thread) Load, check and warm up the planned policies; hand them (or the error) to
        ``start_deciding`` in the executor's thread."""
        try:
            from exit_decision.driving.policy import load_drivers
            self.loaded = load_drivers(self.config, self.policy_dir, self.selection.planned, self.shield,
                                       self.selection.mode)
        except Exception as error:  # noqa: BLE001 (handed to the executor's thread, which stops the node with it)
            self.loaded = error
        self.loaded_signal.trigger()

    def start_deciding(self) -> None:
        """(Executor) With the policies loaded, subscribe and offer the commands; a loading
        error stops the node (``run_node`` says why)."""
        if isinstance(self.loaded, Exception):
            raise self.loaded
        import torch
        torch.set_num_threads(1)   # per thread: this one decides
        self.drivers = self.loaded
        self.bind_mode()   # a set during loading chose the mode the drivers were made in, or another
        self.destroy_guard_condition(self.loaded_signal)
        self.publisher = self.create_publisher(CavCommandArray, COMMANDS_TOPIC, COMMANDS_QOS)
        self.overrides_publisher = self.create_publisher(ShieldOverrideArray, OVERRIDES_TOPIC, COMMANDS_QOS)
        self.options_publisher = self.create_publisher(CavOptionArray, OPTIONS_TOPIC, COMMANDS_QOS)
        if not self.composed:   # events first: the node's wait empties the subscription created first first
            self.intake = Intake.of_config(self, self.diagnostics, self.config)
            starts = self.diagnostics.episode_starts(self.pairing.announce)   # read from the bytes: events_cdr
            self.events = self.intake.subscribe(EpisodeEvent, EPISODE_TOPIC, starts, EVENT_QOS, raw=True)
            self.intake.subscribe(GraphMsg, GRAPH_TOPIC, self.on_graph, GRAPH_QOS, with_info=True)
            self.intake.subscribe(VehicleStateArray, STATES_TOPIC, self.on_states, STATES_QOS, raw=True,
                                  with_info=True)
        for callback in self.when_loaded:
            callback()
        self.get_logger().info(f'loaded {len(self.drivers)} policies from {self.policy_dir}; '
                               f'active: {self.selection.algorithm}/{self.selection.mode.name}')

    def complete_parameters(self, parameters: list[Parameter]) -> list[Parameter]:
        given = {p.name: p.value for p in parameters if p.name in SELECTION_PARAMETERS}
        added = {k: v for k, v in self.selection.completed(given).items() if k not in given}
        return parameters + [Parameter(name, value=value) for name, value in added.items()]

    def validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        changes = {p.name: p.value for p in parameters if p.name in SELECTION_PARAMETERS}
        problem = self.selection.problem(changes) if changes else None
        return SetParametersResult(successful=problem is None, reason=problem or '')

    def apply_parameters(self, parameters: list[Parameter]) -> None:
        changes = {p.name: p.value for p in parameters if p.name in SELECTION_PARAMETERS}
        if changes:
            self.selection.apply(changes)
            self.bind_mode()
            s = self.selection
            self.get_logger().info(f'active policy now {s.algorithm}/{s.mode.name} {s.mode.weights.tolist()}')

    def bind_mode(self) -> None:
        """The active driver drives in the selection's mode; every option held ends (a switch)."""
        for key, driver in self.drivers.items():
            driver.set_mode(self.selection.mode) if key == self.selection.key else driver.reset()

    def begin_episode(self, episode: int) -> None:
        """An episode's first graph or states: the streams follow it, no option is held."""
        self.pairing.start(episode)
        self.last_decided = (episode, -1)
        self.bind_mode()   # no option held

    def on_states(self, raw: bytes, info: dict) -> None:
        gate = self.pairing.states_gate
        states = self.diagnostics.take_states(raw, gate, self.events, self.limits, every=self.interval,
                                              received=info['received_timestamp'])
        if states is None:
            return                                  # only decision steps are used, checked
        key = (states.episode, states.step)
        if gate.begins(*key):
            self.begin_episode(states.episode)
        self.diagnostics.count('skipped_states', gate.accept(*key) // self.interval)
        self.decide_pair(key, self.pairing.add(self.pairing.states, key, states.vehicles))

    def on_graph(self, msg: GraphMsg, info: dict) -> None:
        gate, key = self.pairing.graph_gate, (msg.episode, msg.step)
        if msg.step % self.interval or self.diagnostics.out_of_sequence(gate, self.events, *key, 'graphs',
                                                                        info['received_timestamp']):
            return
        try:
            graph = graph_from_msg(msg, expected_nodes=self.num_nodes, expected_features=self.num_features)
        except InputError as error:
            self.diagnostics.reject('graphs', f'graph of step {msg.step}', str(error), GRAPH_TOPIC)
            return
        if gate.begins(*key):
            self.begin_episode(msg.episode)
        self.diagnostics.count('skipped_graphs', gate.accept(*key) // self.interval)
        self.decide_pair(key, self.pairing.add(self.pairing.graphs, key, (graph, msg.header.stamp)))

    def decide_pair(self, key: tuple[int, int], pair: tuple | None) -> None:
        if pair is not None:
            (graph, stamp), vehicles = pair
            self.decide(key, graph, TrafficSnapshot(vehicles), stamp)

    def decide(self, key: tuple[int, int], graph: TrafficGraph, snapshot: TrafficSnapshot, stamp) -> None:
        """Decide the step ``key`` = (episode, step) once, and publish the commands, then the
        shield's overrides or the options held."""
        if key <= self.last_decided:
            return
        self.last_decided = key
        s, driver = self.selection, self.drivers[self.selection.key]
        try:
            decision = driver.decide(graph, snapshot, key[1] * self.step_length)
        except KeyError as error:   # a CAV of the graph is not in the states
            self.diagnostics.reject('graphs', f'graph of step {key[1]}', f'vehicle {error} is not in the states')
            return
        stamped = {'episode': key[0], 'step': key[1], 'stamp': stamp}
        labels = {'mode': s.mode.name, 'algorithm': s.algorithm, 'policy': str(driver.source.policy.path)}
        self.publisher.publish(encode_commands(decision.commands, **stamped, **labels))
        self.diagnostics.count('decisions', len(decision.commands))
        self.diagnostics.count('shield_overrides', len(decision.overrides))
        if decision.overrides:   # after the commands they belong to
            self.overrides_publisher.publish(overrides_to_msg(decision.overrides, **stamped))
        if decision.options is not None:
            self.options_publisher.publish(options_to_msg(decision.options, **stamped, **labels))


def main() -> int:
    return run_node('decision_node', DecisionNode)


if __name__ == '__main__':
    raise SystemExit(main())
