"""Every custom message crosses rclpy (publish -> subscribe) and converts back to the core types."""
import math
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from exit_decision_msgs.msg import CavCommandArray, TrafficGraph as GraphMsg, VehicleStateArray  # noqa: E402

from exit_decision.config import GraphConfig  # noqa: E402
from exit_decision.graph import GraphBuilder  # noqa: E402
from exit_decision.ros.messages.conversions import (MessageError, commands_from_msg, commands_to_msg,  # noqa: E402
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


# --- vehicle states as CDR bytes (ros/messages/states_cdr.py: what the bridge publishes and the nodes decode) ---

HIGHWAY = ('Highway_0', 'Highway_1', 'Highway_2')


def episode_states(steps: int = 300):
    """Every step's vehicles of a real episode (SUMO's own drivers, so CAVs brake and change lanes)."""
    from exit_decision.config import default_config_dir, load_project
    from exit_decision.env import ExitDecisionEnv
    env = ExitDecisionEnv(load_project(default_config_dir()), cav_driver='sumo')
    try:
        env.reset(seed=10_000)
        result, out = env.sim.state, []
        for _ in range(steps):
            out.append((result.step, result.vehicles))
            result, _ = env.simulate_step(None)
        return out
    finally:
        env.close()


def test_states_encoded_as_cdr_are_the_message_rclpy_reads():
    from rclpy.serialization import deserialize_message, serialize_message

    from exit_decision.ros.messages.states_cdr import decode_states, encode_states
    vehicles_seen = 0
    for step, vehicles in episode_states():
        ours = encode_states(vehicles, episode=3, step=step, step_length=0.1)
        expected = states_to_msg(vehicles, episode=3, step=step, step_length=0.1)
        assert deserialize_message(ours, VehicleStateArray) == expected, f'step {step}'
        decoded = decode_states(serialize_message(expected), HIGHWAY)   # rclpy's bytes, padding and all
        assert decoded.vehicles == states_from_msg(expected, HIGHWAY) == list(vehicles), f'step {step}'
        assert (decoded.episode, decoded.step, decoded.step_length, decoded.stamp) == (
            3, step, 0.1, expected.header.stamp)
        vehicles_seen += len(vehicles)
    assert vehicles_seen > 1000


def test_malformed_cdr_states_are_refused_naming_what():
    from rclpy.serialization import serialize_message

    from exit_decision.ros.messages.states_cdr import decode_states, encode_states
    vehicles = sample_vehicles()
    little = encode_states(vehicles, episode=1, step=5, step_length=0.1)
    assert decode_states(little, HIGHWAY).vehicles == vehicles
    with pytest.raises(MessageError, match='not little-endian CDR'):
        decode_states(b'\x00\x00' + little[2:], HIGHWAY)
    with pytest.raises(MessageError, match='not a VehicleStateArray'):
        decode_states(little[:-12], HIGHWAY)   # cut short
    bad = states_to_msg(vehicles, episode=1, step=5, step_length=0.1)
    bad.vehicles[1].lateral_offset = math.inf
    with pytest.raises(MessageError, match="'HV2_1': lateral_offset is not finite"):
        decode_states(serialize_message(bad), HIGHWAY)
    bad.vehicles[1].lateral_offset, bad.vehicles[1].vehicle_class = 0.0, 9
    with pytest.raises(MessageError, match='vehicle_class 9 is not a known class'):
        decode_states(serialize_message(bad), HIGHWAY)
    bad.vehicles[1].vehicle_class, bad.vehicles[1].vehicle_id = 0, 'CAV_3'
    with pytest.raises(MessageError, match='appears twice'):
        decode_states(serialize_message(bad), HIGHWAY)
    unterminated = bytearray(little)
    unterminated[unterminated.index(b'CAV_3\0') + 5] = ord('7')   # read to its length: CAV_37
    with pytest.raises(MessageError, match='not one NUL-terminated string'):
        decode_states(bytes(unterminated), HIGHWAY)


def test_a_message_too_short_for_its_header_is_an_input_error():
    from exit_decision.input_checks import InputError
    from exit_decision.step_gaps import episode_and_step
    with pytest.raises(InputError, match='6 bytes: too short for a header'):
        episode_and_step(b'\x00\x01\x00\x00\x00\x00')


# --- CAV commands as CDR bytes (ros/messages/commands_cdr.py: the decision node encodes, the bridge decodes) ---

def test_commands_encoded_as_cdr_are_the_message_rclpy_reads():
    from rclpy.serialization import deserialize_message, serialize_message

    from exit_decision.ros.messages.commands_cdr import decode_commands, encode_commands
    rng = np.random.default_rng(0)
    for count in (0, 1, 2, 7, 12):   # strings of every length modulo 4 shift what follows them
        commands = {f'CAV_{int(serial)}': CavCommand(int(rng.integers(-1, 2)), float(rng.uniform(-8, 5)))
                    for serial in rng.choice(150, count, replace=False)}
        fields = dict(episode=int(rng.integers(2**32)), step=count * 5, stamp=stamp_of(count * 0.5),
                      mode='CON' + 'P' * count, algorithm='mdgqn' + '_x' * count, policy='p' * (count + 1))
        ours = encode_commands(commands, **fields)
        theirs = serialize_message(commands_to_msg(commands, **fields))   # rclpy's bytes, padding and all
        expected = deserialize_message(theirs, CavCommandArray)   # accelerations as float32
        assert deserialize_message(ours, CavCommandArray) == expected, count
        decoded = decode_commands(theirs)
        assert decoded.commands == commands_from_msg(expected), count
        assert (decoded.episode, decoded.step, decoded.stamp, decoded.mode, decoded.algorithm, decoded.policy) == (
            fields['episode'], fields['step'], fields['stamp'], fields['mode'], fields['algorithm'], fields['policy'])


def test_malformed_cdr_commands_are_refused_naming_what():
    from exit_decision.ros.messages.commands_cdr import decode_commands, encode_commands
    fields = dict(episode=0, step=5, stamp=stamp_of(0.5), mode='AGGI', algorithm='gqn', policy='p')
    good = encode_commands({'CAV_1': CavCommand(0, 1.0), 'CAV_12': CavCommand(1, -2.0), 'CAV_2': CavCommand(0, 0.5)},
                           **fields)
    assert list(decode_commands(good).commands) == ['CAV_1', 'CAV_12', 'CAV_2']
    with pytest.raises(MessageError, match='not little-endian CDR'):
        decode_commands(b'\x00\x00' + good[2:])
    with pytest.raises(MessageError, match='not a CavCommandArray'):
        decode_commands(good[:-8])   # cut short
    with pytest.raises(MessageError, match="'CAV_1' is listed twice"):
        decode_commands(good.replace(b'CAV_2\0', b'CAV_1\0'))   # same length: only the id changes
    for value in (math.inf, math.nan):
        with pytest.raises(MessageError, match="'CAV_1' acceleration is not finite"):
            decode_commands(encode_commands({'CAV_1': CavCommand(0, value)}, **fields))
    unterminated = bytearray(good)
    unterminated[unterminated.index(b'CAV_12\0') + 6] = ord('7')   # read to its length: CAV_127
    with pytest.raises(MessageError, match='not one NUL-terminated string'):
        decode_commands(bytes(unterminated))


def test_episode_events_read_from_cdr_are_what_rclpy_reads_and_nothing_else_passes():
    """The decision path's nodes read an event's episode and kind from its bytes (a flood of
    events would cost each one rclpy's decoding): for frame ids of every length modulo 4 (they
    shift the fields behind them) they are rclpy's, and bytes cut short, padded beyond the
    message, in the other byte order or with a broken frame id are refused."""
    from exit_decision_msgs.msg import EpisodeEvent
    from rclpy.serialization import serialize_message

    from exit_decision.ros.messages.events_cdr import decode_event
    for length in range(6):
        msg = EpisodeEvent(episode=2**32 - 1 - length, seed=-7, event=EpisodeEvent.EVENT_ENDED if length % 2 else 0,
                           truncated=True, steps=123, v_avs=1.5, n_braking=4, braking_steps=9, reward=-2.5)
        msg.header.frame_id = 'f' * length
        raw = serialize_message(msg)
        assert decode_event(raw) == (msg.episode, msg.event), length
        for cut in (1, 4, 8, 9):
            with pytest.raises(MessageError, match='not an EpisodeEvent'):
                decode_event(raw[:-cut])
        with pytest.raises(MessageError, match='more than an EpisodeEvent'):
            decode_event(raw + bytes(4))
        with pytest.raises(MessageError, match='not little-endian CDR'):
            decode_event(b'\x00\x00' + raw[2:])
        unterminated = bytearray(raw)
        unterminated[16 + length] = ord('x')   # the frame id's NUL
        with pytest.raises(MessageError, match='not one NUL-terminated string'):
            decode_event(bytes(unterminated))
