"""graph_builder: vehicle states in, the traffic graph out, with the training's graph module.

Slots are kept per episode (reset when the episode number changes). A malformed state
message is rejected and counted on /diagnostics; the node goes on.
"""
from __future__ import annotations

from exit_decision_msgs.msg import TrafficGraph, VehicleStateArray
from rclpy.node import Node

from exit_decision.graph import GraphBuilder, GraphCapacityError
from exit_decision.ros.common import GRAPH_TOPIC, STATES_TOPIC, STREAM_QOS, Diagnostics, declare_config, run_node
from exit_decision.ros.conversions import MessageError, graph_to_msg, states_from_msg
from exit_decision.scenario.geometry import RoadGeometry


class GraphBuilderNode(Node):
    def __init__(self):
        super().__init__('graph_builder')
        config = declare_config(self)
        road = config.scenario.road
        self.builder = GraphBuilder(config.graph, RoadGeometry.of(road).road_length, road.highway_speed_limit,
                                    road.lane_count)
        self.feature_set = config.graph.feature_set
        self.episode: int | None = None
        self.publisher = self.create_publisher(TrafficGraph, GRAPH_TOPIC, STREAM_QOS)
        self.create_subscription(VehicleStateArray, STATES_TOPIC, self.on_states, STREAM_QOS)
        self.diagnostics = Diagnostics(self, 'graph_builder')

    def on_states(self, msg: VehicleStateArray) -> None:
        try:
            vehicles = states_from_msg(msg)
            if msg.episode != self.episode:
                self.builder.reset()
                self.episode = msg.episode
            graph = self.builder.build(vehicles)
        except (MessageError, GraphCapacityError) as error:
            self.diagnostics.count('rejected_states')
            self.get_logger().warning(f'rejected states of step {msg.step}: {error}', throttle_duration_sec=5.0)
            return
        self.publisher.publish(graph_to_msg(graph, feature_set=self.feature_set, episode=msg.episode,
                                            step=msg.step, stamp=msg.header.stamp))
        self.diagnostics.count('graphs')


def main() -> int:
    return run_node('graph_builder', GraphBuilderNode)


if __name__ == '__main__':
    raise SystemExit(main())
