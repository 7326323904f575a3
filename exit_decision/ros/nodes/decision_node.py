"""decision_node: the trained policy of the active mode drives every CAV.

At start it loads, for each name of parameter ``algorithms`` (any learned method of
config/training.yaml: its checkpoint carries its state encoder): ``<algorithm>_conditioned``
is one mode-conditioned checkpoint (``policy_dir/<algorithm>_conditioned/policy.pt``) that
serves every mode of the config and any ``reward_weights``; a plain ``<algorithm>`` is one
checkpoint per mode of parameter ``modes`` (``policy_dir/<algorithm>_<mode>/policy.pt``). A
missing, corrupt or incompatible file stops the node at start, naming the path. The policies
load (torch's import included, about 2 s here) in a thread once the node is up: its parameter
services answer meanwhile, and it subscribes and creates its command publisher only when they
are loaded, so a synchronous bridge, which waits for a commands publisher, starts after that.

``mode`` and ``reward_weights`` (six numbers: result, efficiency, comfort and safety weights
summing to 1, incentive and punishment summing to 1) are kept consistent: setting a mode sets
its weights, setting weights sets the mode whose weights they are, or ``custom``
(``model.modes``, converted when a parameter is set). Every decision is for the current
weights: a conditioned policy takes new ones at the next decision, with no reload; a per-mode
policy is the one of their mode. Choosing, loading and checking the policies is
``model.policy.load_controllers``'s; this node declares the parameters and wires the callbacks.
On each decision step it pairs the graph with the
vehicle states of the same step (the shield needs gaps and lanes), runs the greedy policy
under the same shield as training and evaluation, and publishes the commands stamped with
mode, algorithm and policy file. ``mode`` and ``algorithm`` switch at runtime through the
standard parameter service: a value without a loaded policy is refused with the reason; an
accepted one is used from the next graph. Diagnostics count decisions, shield overrides of
the network's first choice, and rejected messages; the
CAVs overridden at a decision are published on /exit_decision/shield_overrides.

In the stack it runs composed with the graph builder in one process (``graph_and_decision``),
which hands it each decision step's checked states and graph directly; started alone
(``ros2 run exit_decision decision_node``) it subscribes to both topics. Alone, a graph or a
states message is taken only if it can follow the current episode and step
(the sequence starts afresh at the first message of an episode the bridge's or the player's
EVENT_STARTED announced, and only then)
and every field fits (sizes, finite values, the scenario's lanes, ids and ranges); otherwise
it is rejected whole, counted on /diagnostics and changes nothing.
"""
from __future__ import annotations

import threading
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from exit_decision_msgs.msg import (CavCommandArray, EpisodeEvent, ShieldOverrideArray, TrafficGraph as GraphMsg,
                                    VehicleStateArray)
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from exit_decision.actions import ActionGrid
from exit_decision.agents.shield import Shield
from exit_decision.errors import PolicyError
from exit_decision.graph import FEATURE_SETS, TrafficGraph
from exit_decision.model.modes import CUSTOM_MODE, ModeWeights, check_weights
from exit_decision.model.names import SHIPPED_ALGORITHMS, default_policy_dir, planned, planned_policies
from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import run_node
from exit_decision.ros.parameters import (declare, declare_config, declare_cpu_affinity, declare_thread_priority,
                                          describe)
from exit_decision.ros.topics import (COMMANDS_QOS, COMMANDS_TOPIC, EPISODE_TOPIC, EVENT_QOS, GRAPH_QOS, GRAPH_TOPIC,
                                      OVERRIDES_TOPIC, STATES_QOS, STATES_TOPIC)
from exit_decision.ros.messages.commands_cdr import encode_commands
from exit_decision.ros.messages.conversions import graph_from_msg, overrides_to_msg
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.shield_overrides import shield_overrides
from exit_decision.input_checks import InputError, StateLimits, StepGate
from exit_decision.traffic import TrafficSnapshot

if TYPE_CHECKING:
    from exit_decision.model.policy import PolicyController

PAIRING_WINDOW = 20   # steps of unpaired graphs / states kept while waiting for the other half


class DecisionNode(Node):
    """``composed``: the graph builder of the same process (``graph_and_decision``) tells this
    node when an episode begins and hands it each decision step's checked states with their
    graph (``begin_episode``, ``decide``): it subscribes to neither, and nothing crosses a process."""

    def __init__(self, composed: bool = False):
        super().__init__('decision_node')
        self.composed = composed
        config = declare_config(self)
        declare_thread_priority(self)
        declare_cpu_affinity(self)
        def p(name, default, descriptor):
            return declare(self, name, default, descriptor)
        policy_dir = Path(p('policy_dir', '', describe(
            'directory with <algorithm>_<mode>/policy.pt; empty: the shipped policies', read_only=True))
            or default_policy_dir())
        modes = list(p('modes', config.mode_matrix.modes, describe(
            'modes whose policies are loaded at start', read_only=True)))
        start_algorithm = p('algorithm', '', describe(
            'a learned method of config/training.yaml (per-mode policies <algorithm>_<mode>/) or '
            '<method>_conditioned (one policy, every mode); one of parameter algorithms; empty at start: '
            'the last of parameter algorithms',
            constraints='a learned method of config/training.yaml or <method>_conditioned, loaded at start '
                        '(parameter algorithms)'))
        shipped = not start_algorithm or start_algorithm in SHIPPED_ALGORITHMS
        algorithms = list(p('algorithms', list(SHIPPED_ALGORITHMS) if shipped else [start_algorithm], describe(
            f'algorithms whose policies are loaded at start; default: the shipped ones '
            f'({", ".join(SHIPPED_ALGORITHMS)}), '
            'or only the start algorithm if it is another', read_only=True)))
        if not algorithms:
            raise PolicyError('parameter algorithms: give at least one algorithm')
        if not start_algorithm:
            start_algorithm = algorithms[-1]
            self.set_parameters([Parameter('algorithm', Parameter.Type.STRING, start_algorithm)])
        self.config = config
        self.grid = ActionGrid(config.env.actions)
        geometry = RoadGeometry.of(config.scenario.road)
        self.shield = Shield.of(config, self.grid, geometry)
        self.limits = StateLimits.of(config, geometry)
        if not modes:
            raise PolicyError('parameter modes: give at least one mode')
        #: the policies to load, (algorithm, mode), mode None for a conditioned one: what the
        #: parameters are checked against, also while they load
        self.planned = planned_policies(algorithms, modes)
        self.mode_weights = ModeWeights(config)
        for _, mode in self.planned:
            if mode is not None:
                self.mode_weights.weights(mode)   # an unknown one stops the node now, not after loading
        self.controllers: dict[tuple[str, str | None], PolicyController] = {}   # filled once loaded
        self.mode = p('mode', modes[0], describe(
            'decision mode', constraints=' | '.join([*config.modes, CUSTOM_MODE])))
        if not isinstance(self.mode, str) or self.mode not in config.modes and self.mode != CUSTOM_MODE:
            raise PolicyError(f'parameter mode: {self.mode!r} is not allowed; allowed: {" | ".join(config.modes)}')
        start_weights = self.mode_weights.weights(self.mode if self.mode in config.modes else modes[0])
        reward_weights = list(p('reward_weights', start_weights.tolist(), describe(
            'the mode\'s weights: result, efficiency, comfort, safety (sum 1), incentive, punishment '
            '(sum 1); a conditioned policy decides for any such point; given at start, they name the mode')))
        reason = check_weights(reward_weights)
        if reason:
            raise PolicyError(f'reward_weights {reward_weights}: {reason}')
        #: what every decision is for (parameter reward_weights)
        self.weights = np.asarray(reward_weights, dtype=float)
        named = self.mode_weights.name(self.weights)
        if named != self.mode:
            # weights given at start win: the mode is named after them
            self.mode = named
            self.set_parameters([Parameter('mode', Parameter.Type.STRING, self.mode)])
        self.algorithm = start_algorithm
        problem = self.problem({})
        if problem:
            raise PolicyError(problem)
        self.interval = config.env.decision_interval
        self.num_nodes = config.graph.max_vehicles
        self.num_features = len(FEATURE_SETS[config.graph.feature_set])
        self.add_pre_set_parameters_callback(self.complete_parameters)
        self.add_on_set_parameters_callback(self.validate_parameters)
        self.add_post_set_parameters_callback(self.apply_parameters)
        #: checked graphs (with their stamp) and vehicle states of decision steps, waiting for the other half
        self.graphs: dict[tuple[int, int], tuple] = {}
        self.states: dict[tuple[int, int], list] = {}
        self.last_decided: tuple[int, int] = (-1, -1)
        gap = 2 * self.interval   # one decision step may go missing without a resync
        self.graph_gate = StepGate(config.scenario.max_steps, max_gap=gap)
        self.states_gate = StepGate(config.scenario.max_steps, max_gap=gap)
        self.diagnostics = Diagnostics(self, 'decision_node')
        self.policy_dir, self.modes = policy_dir, modes
        self.loaded: dict | Exception | None = None   # what the loading thread hands over: the controllers
        self.when_loaded: list = []   # called once the policies are loaded (composed: the graph builder subscribes)
        self.loaded_signal = self.create_guard_condition(self.start_deciding)
        threading.Thread(target=self.load_policies, name='load_policies', daemon=True).start()

    # --- start ------------------------------------------------------------------------------

    def load_policies(self) -> None:
        """(Thread) Load, check and warm up the planned policies; hand them (or the error) to
        ``start_deciding`` in the executor's thread."""
        try:
            from exit_decision.agents.lane_planner import LanePlanner
            from exit_decision.model.policy import load_controllers
            config = self.config
            # each controller sets torch to one thread, in this thread: the warm-up as the decisions will run
            controllers = load_controllers(config, self.policy_dir, self.planned, self.shield,
                                           LanePlanner.of(config, self.shield))
            n, f = config.graph.max_vehicles, len(FEATURE_SETS[config.graph.feature_set])
            idle = TrafficGraph(np.zeros((n, f), np.float32), np.zeros((n, n), np.uint8), np.zeros(n, bool),
                                ('',) * n)
            warm = self.mode_weights.weights(self.modes[0])
            for controller in controllers.values():   # the first forward pass is slow: not on the first decision
                controller.policy.q_values(idle, TrafficSnapshot([]), warm if controller.policy.conditioned else None)
            self.loaded = controllers
        except Exception as error:  # noqa: BLE001 (handed to the executor's thread, which stops the node with it)
            self.loaded = error
        self.loaded_signal.trigger()

    def start_deciding(self) -> None:
        """(Executor) With the policies loaded, subscribe and offer the commands; a loading
        error stops the node (``run_node`` says why)."""
        if isinstance(self.loaded, Exception):
            raise self.loaded
        import torch
        torch.set_num_threads(1)   # per thread: this one decides (the controllers set the loading thread's)
        self.controllers = self.loaded
        self.destroy_guard_condition(self.loaded_signal)
        self.publisher = self.create_publisher(CavCommandArray, COMMANDS_TOPIC, COMMANDS_QOS)
        self.overrides_publisher = self.create_publisher(ShieldOverrideArray, OVERRIDES_TOPIC, COMMANDS_QOS)
        if not self.composed:
            # events first: when an episode's start and its first messages are both waiting, the
            # node's wait (executor.Waiter) empties the queue of the subscription created first first
            self.events = self.diagnostics.subscribe(EpisodeEvent, EPISODE_TOPIC, self.on_episode, EVENT_QOS)
            self.diagnostics.subscribe(GraphMsg, GRAPH_TOPIC, self.on_graph, GRAPH_QOS)
            self.diagnostics.subscribe(VehicleStateArray, STATES_TOPIC, self.on_states, STATES_QOS, raw=True)
        for callback in self.when_loaded:
            callback()
        self.get_logger().info(f'loaded {len(self.controllers)} policies from {self.policy_dir}; '
                               f'active: {self.algorithm}/{self.mode}')

    # --- parameters -------------------------------------------------------------------------

    def complete_parameters(self, parameters: list[Parameter]) -> list[Parameter]:
        """Keep mode and reward_weights consistent: setting one sets the other too (values of
        the wrong type are left for the validation to refuse)."""
        names = {p.name for p in parameters}
        if 'mode' in names and 'reward_weights' not in names:
            mode = next(p.value for p in parameters if p.name == 'mode')
            if isinstance(mode, str) and mode in self.mode_weights:
                parameters.append(Parameter('reward_weights', Parameter.Type.DOUBLE_ARRAY,
                                            self.mode_weights.weights(mode).tolist()))
        elif 'reward_weights' in names and 'mode' not in names:
            weights = next(p.value for p in parameters if p.name == 'reward_weights')
            if check_weights(weights) is None:
                parameters.append(Parameter('mode', Parameter.Type.STRING, self.mode_weights.name(weights)))
        return parameters

    def problem(self, changes: dict) -> str | None:
        """Why the parameters with these changes cannot drive (None if they can)."""
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
        named = self.mode_weights.name(chosen['reward_weights'])
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

    def validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse a mode, algorithm or reward_weights the loaded policies cannot drive with."""
        changes = {p.name: p.value for p in parameters if p.name in ('mode', 'algorithm', 'reward_weights')}
        problem = self.problem(changes) if changes else None
        return SetParametersResult(successful=problem is None, reason=problem or '')

    def apply_parameters(self, parameters: list[Parameter]) -> None:
        for parameter in parameters:
            if parameter.name in ('mode', 'algorithm'):
                setattr(self, parameter.name, parameter.value)
            elif parameter.name == 'reward_weights':
                self.weights = np.asarray(parameter.value, dtype=float)
        if any(p.name in ('mode', 'algorithm', 'reward_weights') for p in parameters):
            self.get_logger().info(f'active policy now {self.algorithm}/{self.mode} {self.weights.tolist()}')

    # --- messages ---------------------------------------------------------------------------

    def on_episode(self, msg: EpisodeEvent) -> None:
        if msg.event == EpisodeEvent.EVENT_STARTED:
            for gate in (self.graph_gate, self.states_gate):
                gate.announce(msg.episode)

    def begin_episode(self, episode: int) -> None:
        """The first graph or states of an announced episode came: both streams follow it from
        its start (a late message of the pass before is refused on either), and nothing of the
        pass before is paired or counted as decided."""
        for gate in (self.graph_gate, self.states_gate):
            gate.start(episode)
        self.graphs.clear()
        self.states.clear()
        self.last_decided = (episode, -1)

    def on_states(self, raw: bytes) -> None:
        states = self.diagnostics.take_states(raw, self.states_gate, self.events, self.limits, every=self.interval)
        if states is None:
            return                                  # only decision steps are used, checked
        episode, step, vehicles = states.episode, states.step, states.vehicles
        if self.states_gate.begins(episode, step):
            self.begin_episode(episode)
        self.diagnostics.count('skipped_states', self.states_gate.accept(episode, step) // self.interval)
        self.states[(episode, step)] = vehicles
        self.try_decide((episode, step))

    def on_graph(self, msg: GraphMsg) -> None:
        if msg.step % self.interval:
            return
        if self.diagnostics.out_of_sequence(self.graph_gate, self.events, msg.episode, msg.step, 'graphs'):
            return
        try:
            graph = graph_from_msg(msg, expected_nodes=self.num_nodes, expected_features=self.num_features)
        except InputError as error:
            self.diagnostics.reject('graphs', f'graph of step {msg.step}', str(error))
            return
        if self.graph_gate.begins(msg.episode, msg.step):
            self.begin_episode(msg.episode)
        self.diagnostics.count('skipped_graphs', self.graph_gate.accept(msg.episode, msg.step) // self.interval)
        self.graphs[(msg.episode, msg.step)] = (graph, msg.header.stamp)
        self.try_decide((msg.episode, msg.step))

    def try_decide(self, key: tuple[int, int]) -> None:
        if key not in self.graphs or key not in self.states:
            self.forget_before((key[0], key[1] - PAIRING_WINDOW * self.interval))
            return
        (graph, stamp), vehicles = self.graphs.pop(key), self.states.pop(key)
        self.forget_before(key)
        self.decide(key, graph, TrafficSnapshot(vehicles), stamp)

    def decide(self, key: tuple[int, int], graph: TrafficGraph, snapshot: TrafficSnapshot, stamp) -> None:
        """Decide the step ``key`` = (episode, step) from its graph and checked states, and
        publish the commands (then the shield's overrides), once per step."""
        if key <= self.last_decided:
            return
        self.last_decided = key
        controller = self.controllers[planned(self.algorithm, self.mode)]
        try:
            decision = controller.decide(graph, snapshot, self.weights)
        except KeyError as error:   # a CAV of the graph is not in the states
            self.diagnostics.reject('graphs', f'graph of step {key[1]}', f'vehicle {error} is not in the states')
            return
        commands = {vehicle_id: self.grid.command(index) for vehicle_id, index in decision.actions.items()}
        self.publisher.publish(encode_commands(commands, episode=key[0], step=key[1], stamp=stamp, mode=self.mode,
                                               algorithm=self.algorithm, policy=str(controller.policy.path)))
        self.diagnostics.count('decisions', len(commands))
        self.diagnostics.count('shield_overrides', decision.overridden)
        overrides = shield_overrides(decision, self.grid)
        if overrides:   # after the commands they belong to
            self.overrides_publisher.publish(overrides_to_msg(overrides, episode=key[0], step=key[1], stamp=stamp))

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
