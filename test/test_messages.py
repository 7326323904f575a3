"""Every custom message crosses rclpy (publish -> subscribe) and converts back to the core types."""
import math
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from exit_decision_msgs.msg import CavCommandArray, TrafficGraph as GraphMsg, VehicleStateArray  # noqa: E402

from exit_decision.config import GraphConfig  # noqa: E402
from exit_decision.graph import GraphBuilder  # noqa: E402
from exit_decision.ros.conversions import (MessageError, commands_from_msg, commands_to_msg,  # noqa: E402
                                           graph_from_msg, graph_to_msg, stamp_of, states_from_msg,
                                           states_to_msg)
from exit_decision.traffic import CavCommand  # noqa: E402

from conftest import make_vehicle  # noqa: E402


@pytest.fixture()
def node():
    context = rclpy.context.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('message_test', context=context)
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.executor_for_test = executor
    yield node
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def round_trip(node, msg_type, msg, topic):
    received = []
    node.create_subscription(msg_type, topic, received.append, 10)
    publisher = node.create_publisher(msg_type, topic, 10)
    deadline = time.monotonic() + 10.0
    while not received and time.monotonic() < deadline:
        publisher.publish(msg)
        node.executor_for_test.spin_once(timeout_sec=0.05)
    assert received, f'nothing received on {topic}'
    return received[0]


def sample_vehicles():
    return [make_vehicle('CAV_3', 'CAV', lane=2, position=120.5, speed=21.5, acceleration=-1.5, intention=-1),
            make_vehicle('HV2_1', 'HV2', lane=1, position=101.0, speed=22.0, edge='Highway_1')]


def test_vehicle_state_array(node):
    msg = states_to_msg(sample_vehicles(), episode=2, step=42, step_length=0.1)
    got = round_trip(node, VehicleStateArray, msg, 'test_states')
    assert (got.episode, got.step) == (2, 42)
    assert got.header.stamp.sec == 4 and got.header.stamp.nanosec == 200_000_000
    assert states_from_msg(got, ('Highway_0', 'Highway_1', 'Highway_2')) == sample_vehicles()


def test_traffic_graph(node):
    graph = GraphBuilder(GraphConfig(max_vehicles=60, sensing_range=30.0, feature_set='paper'),
                         road_length=516.7, speed_scale=25.0).build(sample_vehicles())
    msg = graph_to_msg(graph, feature_set='paper', episode=0, step=7, stamp=stamp_of(0.7))
    got = graph_from_msg(round_trip(node, GraphMsg, msg, 'test_graph'), expected_nodes=60, expected_features=8)
    np.testing.assert_array_equal(got.features, graph.features)
    np.testing.assert_array_equal(got.adjacency, graph.adjacency)
    np.testing.assert_array_equal(got.cav_mask, graph.cav_mask)
    assert got.vehicle_ids == graph.vehicle_ids


def test_cav_command_array(node):
    commands = {'CAV_3': CavCommand(1, -2.5), 'CAV_4': CavCommand(0, 5.0)}
    msg = commands_to_msg(commands, episode=1, step=9, stamp=stamp_of(0.9), mode='AGGI', algorithm='mdgqn',
                          policy='policies/mdgqn_AGGI.pt')
    got = round_trip(node, CavCommandArray, msg, 'test_commands')
    assert (got.mode, got.algorithm, got.policy) == ('AGGI', 'mdgqn', 'policies/mdgqn_AGGI.pt')
    assert commands_from_msg(got) == commands


def test_malformed_messages_are_rejected_naming_the_field():
    graph = GraphMsg(num_nodes=3, num_features=8, vehicle_ids=['', '', ''])
    graph.features = np.zeros(20, dtype=np.float32)
    with pytest.raises(MessageError, match='features has 20 entries, expected 24'):
        graph_from_msg(graph)
    with pytest.raises(MessageError, match='num_nodes is 3, the policy expects 60'):
        graph_from_msg(graph, expected_nodes=60)
    bad_speed = states_to_msg([make_vehicle('x', speed=1.0)], episode=0, step=0, step_length=0.1)
    bad_speed.vehicles[0].speed = math.nan
    with pytest.raises(MessageError, match="'x': speed is not finite"):
        states_from_msg(bad_speed, ('Highway_0',))
    commands = commands_to_msg({'CAV_1': CavCommand(0, 0.0)}, episode=0, step=0, stamp=stamp_of(0.0),
                               mode='AGGI', algorithm='gqn', policy='p')
    commands.commands[0].acceleration = math.inf
    with pytest.raises(MessageError, match="'CAV_1' acceleration is not finite"):
        commands_from_msg(commands)
