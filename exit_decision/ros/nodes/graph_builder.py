"""graph_builder: vehicle states in, the traffic graph out, with the training's graph module.

A graph is built and published for the decision steps only (every ``decision_interval``
steps), from their states alone, exactly as the environment builds it in training and
evaluation: the same rows (slots) for the same vehicles. The states of the steps between are
not even decoded (their (episode, step) is read from the raw message): nobody uses their graph.

Slots are kept per episode: they and the step sequence start afresh at the first states of an
episode the bridge (or the player) announced with an EVENT_STARTED, and only then (an
EVENT_STARTED that no states of its episode follow changes nothing). A state message is taken
only if it can follow the current episode and step and every field fits the scenario
(``exit_decision.input_checks``); otherwise it is rejected whole, counted on /diagnostics and
changes nothing.
"""
from __future__ import annotations

from functools import partial
from typing import TYPE_CHECKING

from exit_decision_msgs.msg import EpisodeEvent, TrafficGraph, VehicleStateArray
from rclpy.node import Node

from exit_decision.graph import GraphBuilder, GraphCapacityError, GraphInputError
from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import run_node
from exit_decision.ros.intake import Intake
from exit_decision.ros.parameters import declare_config, declare_cpu_affinity, declare_thread_priority
from exit_decision.ros.topics import EPISODE_TOPIC, EVENT_QOS, GRAPH_QOS, GRAPH_TOPIC, STATES_QOS, STATES_TOPIC
from exit_decision.ros.messages.conversions import graph_to_msg
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.input_checks import StateLimits, StepGate
from exit_decision.traffic import TrafficSnapshot

if TYPE_CHECKING:
    from exit_decision.ros.nodes.decision_node import DecisionNode


class GraphBuilderNode(Node):
    """``decision``: the decision node composed in the same process (``graph_and_decision``),
    or None. It gets the episode events and each graph with its checked states directly, and
    decides before the graph is published (for the recorder and the visualizer). Composed, the
    graph builder subscribes once the decision node has loaded its policies, as the decision
    node alone does: a bridge waiting for its listeners (any timing) starts only then."""

    def __init__(self, decision: DecisionNode | None = None):
        super().__init__('graph_builder')
        self.decision = decision
        config = declare_config(self)
        declare_thread_priority(self)
        declare_cpu_affinity(self)
        road = config.scenario.road
        geometry = RoadGeometry.of(road)
        # a new episode's first graph is built by a fresh builder, kept only if that graph is built
        self.new_builder = partial(GraphBuilder, config.graph, geometry.road_length, road.highway_speed_limit,
                                   road.lane_count)
        self.builder = self.new_builder()
        self.limits = StateLimits.of(config, geometry)
        self.interval = config.env.decision_interval
        self.gate = StepGate(config.scenario.max_steps, max_gap=2 * self.interval)   # one decision step may go missing
        self.feature_set = config.graph.feature_set
        self.diagnostics = Diagnostics(self, 'graph_builder')
        self.intake = Intake.of_config(self, self.diagnostics, config)
        self.publisher = self.create_publisher(TrafficGraph, GRAPH_TOPIC, GRAPH_QOS)
        if decision is None:
            self.subscribe()
        else:
            decision.when_loaded.append(self.subscribe)

    def subscribe(self) -> None:
        # events first: when an episode's start and its first states are both waiting, the
        # node's wait (executor.Waiter) empties the queue of the subscription created first first
        starts = self.diagnostics.episode_starts(self.gate.announce)   # read from the bytes: events_cdr
        self.events = self.intake.subscribe(EpisodeEvent, EPISODE_TOPIC, starts, EVENT_QOS, raw=True)
        self.intake.subscribe(VehicleStateArray, STATES_TOPIC, self.on_states, STATES_QOS, raw=True,
                              with_info=True)

    def on_states(self, raw: bytes, info: dict) -> None:
        states = self.diagnostics.take_states(raw, self.gate, self.events, self.limits, every=self.interval,
                                              received=info['received_timestamp'])
        if states is None:
            return
        episode, step = states.episode, states.step
        begins = self.gate.begins(episode, step)
        builder = self.new_builder() if begins else self.builder
        # one neighbour index for the graph and the decision (alone, the builder makes one if its features need it)
        snapshot = TrafficSnapshot(states.vehicles) if self.decision is not None else None
        try:
            graph = builder.build(states.vehicles, snapshot)
        except (GraphInputError, GraphCapacityError) as error:
            self.diagnostics.reject('states', f'states of step {step}', str(error), STATES_TOPIC)
            return
        self.builder = builder
        self.diagnostics.count('skipped_decision_steps', self.gate.accept(episode, step) // self.interval)
        if self.decision is not None:
            if begins:
                self.decision.begin_episode(episode)
            self.decision.decide((episode, step), graph, snapshot, states.stamp)
        self.publisher.publish(graph_to_msg(graph, feature_set=self.feature_set, episode=episode, step=step,
                                            stamp=states.stamp))
        self.diagnostics.count('graphs')


def main() -> int:
    return run_node('graph_builder', GraphBuilderNode)


if __name__ == '__main__':
    raise SystemExit(main())
