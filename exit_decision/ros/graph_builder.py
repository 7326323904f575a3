"""graph_builder: vehicle states in, the traffic graph out, with the training's graph module.

Slots are kept per episode: they and the step sequence start afresh on the bridge's (or the
player's) EVENT_STARTED, and only then. A state message is taken only if it can follow the
current episode and step and every field fits the scenario (``exit_decision.input_checks``);
otherwise it is rejected whole, counted on /diagnostics and changes nothing.
"""
from __future__ import annotations

from exit_decision_msgs.msg import EpisodeEvent, TrafficGraph, VehicleStateArray
from rclpy.node import Node

from exit_decision.graph import GraphBuilder, GraphCapacityError, GraphInputError
from exit_decision.ros.common import (EPISODE_TOPIC, EVENT_QOS, GRAPH_QOS, GRAPH_TOPIC, STATES_QOS, STATES_TOPIC,
                                      Diagnostics, declare_config, run_node)
from exit_decision.ros.conversions import checked_states, graph_to_msg
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.input_checks import InputError, StateLimits, StepGate


class GraphBuilderNode(Node):
    def __init__(self):
        super().__init__('graph_builder')
        config = declare_config(self)
        road = config.scenario.road
        geometry = RoadGeometry.of(road)
        self.builder = GraphBuilder(config.graph, geometry.road_length, road.highway_speed_limit, road.lane_count)
        self.limits = StateLimits.of(config, geometry)
        self.gate = StepGate(config.scenario.max_steps)
        self.feature_set = config.graph.feature_set
        self.diagnostics = Diagnostics(self, 'graph_builder')
        self.publisher = self.create_publisher(TrafficGraph, GRAPH_TOPIC, GRAPH_QOS)
        # events first: when an episode's start and its first states are both waiting, the
        # executor takes the subscription created first
        self.create_subscription(EpisodeEvent, EPISODE_TOPIC, self.on_episode, EVENT_QOS)
        self.diagnostics.subscribe(VehicleStateArray, STATES_TOPIC, self.on_states, STATES_QOS)

    def on_episode(self, msg: EpisodeEvent) -> None:
        if msg.event == EpisodeEvent.EVENT_STARTED:
            self.gate.start(msg.episode)
            self.builder.reset()

    def on_states(self, msg: VehicleStateArray) -> None:
        reason = self.gate.refuse(msg.episode, msg.step)
        if reason:
            self.diagnostics.reject('out_of_sequence_states', 'states', reason)
            return
        try:
            graph = self.builder.build(checked_states(msg, self.limits))
        except (InputError, GraphInputError, GraphCapacityError) as error:
            self.diagnostics.reject('states', f'states of step {msg.step}', str(error))
            return
        self.diagnostics.count('skipped_steps', self.gate.accept(msg.step))
        self.publisher.publish(graph_to_msg(graph, feature_set=self.feature_set, episode=msg.episode,
                                            step=msg.step, stamp=msg.header.stamp))
        self.diagnostics.count('graphs')


def main() -> int:
    return run_node('graph_builder', GraphBuilderNode)


if __name__ == '__main__':
    raise SystemExit(main())
