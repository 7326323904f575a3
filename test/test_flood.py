"""Bounded intake (issue 40): size limits from N and the layout, drops counted by cause, the
recorder refusing what is over the limit, and the stack under a flood (``bench flood``'s run,
short, on the states topic): commands keep coming, memory stays bounded, every drop is counted.
No timing is asserted here: the rate and wait targets are the bench's (``exit-decision bench flood``)."""
import json

import yaml
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from exit_decision_msgs.msg import CavCommandArray, EpisodeEvent, TrafficGraph, VehicleStateArray
from rclpy.duration import Duration
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message

from exit_decision.config import default_config_dir, load_project
from exit_decision.graph import FEATURE_SETS
from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.intake import Intake
from exit_decision.ros.messages.commands_cdr import encode_commands
from exit_decision.ros.messages.sizes import NAME_BYTES, limits_of
from exit_decision.ros.messages.states_cdr import encode_states
from exit_decision.ros.nodes.recorder import REFUSED_KEY
from exit_decision.ros.probe import ProbeNode
from exit_decision.ros.stack.flood import MEMORY_MB, bench_flood
from exit_decision.ros.stack.flooder import padded
from exit_decision.ros.stack.launcher import start_node
from exit_decision.ros.topic_names import CLOCK_TOPIC
from exit_decision.ros.topics import COMMANDS_TOPIC, EPISODE_TOPIC, EVENT_QOS, GRAPH_TOPIC, STATES_TOPIC, STREAM_QOS
from exit_decision.traffic import CavCommand, VehicleState

from ros_helpers import stop


def test_the_size_limits_hold_the_largest_messages_the_stack_sends():
    """N vehicles with long names, a full N x N graph, N commands with a long policy path: each
    within its topic's limit; one byte more than a limit is over it."""
    config = load_project(default_config_dir())
    limits, n = limits_of(config), config.graph.max_vehicles
    name = 'x' * NAME_BYTES
    vehicles = [VehicleState(f'{name[:-3]}{i:03d}', 'HV1', 2, name, 1e4, -1.0, 40.0, -9.0, 5.0, 25.0, -1, name,
                             False, True) for i in range(n)]
    states = encode_states(vehicles, episode=2**32 - 1, step=2**32 - 1, step_length=0.1, frame_id=name)
    features = len(FEATURE_SETS[config.graph.feature_set])
    graph = serialize_message(TrafficGraph(
        num_nodes=n, num_features=features, feature_set=name, vehicle_ids=[name] * n, features=[1.0] * (n * features),
        adjacency=bytes([1]) * (n * n), cav_mask=bytes([1]) * n))
    commands = encode_commands({f'{name[:-3]}{i:03d}': CavCommand(1, -8.0) for i in range(n)}, episode=1, step=5,
                               stamp=Time(), mode=name, algorithm=name, policy='/p' * 2000)
    for topic, message in ((STATES_TOPIC, states), (GRAPH_TOPIC, graph), (COMMANDS_TOPIC, commands)):
        assert len(message) <= limits[topic], (topic, len(message), limits[topic])
        assert len(padded(message, limits[topic] + 1)) > limits[topic]


def test_the_intake_refuses_what_is_too_large_or_undecodable_and_counts_it_by_topic_and_cause():
    config = load_project(default_config_dir())
    limit = limits_of(config)[EPISODE_TOPIC]
    probe = ProbeNode('intake_test')
    try:
        diagnostics = Diagnostics(probe.node, 'intake_test')
        taken = []
        Intake(probe.node, diagnostics, limits_of(config)).subscribe(EpisodeEvent, EPISODE_TOPIC, taken.append,
                                                                     EVENT_QOS)
        publisher = probe.node.create_publisher(EpisodeEvent, EPISODE_TOPIC, EVENT_QOS)
        assert probe.spin_until(lambda: publisher.get_subscription_count() > 0, 10)
        good = serialize_message(EpisodeEvent(episode=3))
        for message in (good, padded(good, limit + 1), b'\x00\x01\x00\x00\xff', good):
            publisher.publish(message)
        assert probe.spin_until(lambda: diagnostics.counters.get('received_episode_events') == 4, 10), \
            diagnostics.counters
        assert [msg.episode for msg in taken] == [3, 3]
        assert diagnostics.counters['dropped_episode_events_too_large'] == 1
        assert diagnostics.counters['dropped_episode_events_undecodable'] == 1
    finally:
        probe.close()


def test_a_serialized_take_gives_the_bytes_the_sequence_number_the_time_and_the_publishers_gid():
    """``take.SerializedTake`` (rcl's take, looped in C) against what rclpy knows: the same bytes
    as rclpy's own take, consecutive sequence numbers, a source time within the publish call and
    the gid the graph lists for the publisher (so the structures' fields sit where rcl puts them);
    a message over the size limit is dropped there, recorded with its gid, number and length."""
    import time

    from exit_decision.ros.take import MESSAGE_WAITING, QUEUE_EMPTY, TOO_LARGE, SerializedTake
    probe = ProbeNode('serialized_take_test')
    try:
        qos = QoSProfile(depth=10)
        subscription = probe.node.create_subscription(EpisodeEvent, '/serialized_take_test', lambda *_: None, qos,
                                                      raw=True)
        publisher = probe.node.create_publisher(EpisodeEvent, '/serialized_take_test', qos)
        assert probe.spin_until(lambda: publisher.get_subscription_count() > 0, 10)
        messages = [serialize_message(EpisodeEvent(episode=episode)) for episode in (7, 8)]
        before = time.time_ns()
        for message in messages:
            publisher.publish(message)
        after = time.time_ns()
        (gid,) = [bytes(info.endpoint_gid[:16]) for info in probe.node.get_publishers_info_by_topic(
            '/serialized_take_test')]
        deadline = time.monotonic() + 10
        take = SerializedTake()
        with subscription.handle:
            while (first := subscription.handle.take_message(EpisodeEvent, True)) is None \
                    and time.monotonic() < deadline:
                time.sleep(0.01)
            while take.drain(subscription) != (MESSAGE_WAITING, 0) and time.monotonic() < deadline:
                time.sleep(0.01)
            second = take.waiting()
        assert (first[0], second[0]) == tuple(messages)
        assert second[1]['publication_sequence_number'] == first[1]['publication_sequence_number'] + 1
        assert before <= second[1]['source_timestamp'] <= after <= second[1]['received_timestamp'] + 10 ** 9
        assert second[1]['publisher_gid'] == gid
        # over a size limit a message is dropped in C, recorded; at the limit, it waits for Python
        size, number = len(messages[0]), second[1]['publication_sequence_number']
        for _ in range(2):
            publisher.publish(messages[0])
        publisher.publish(messages[1])
        dropped = []
        with subscription.handle:
            while len(dropped) < 3 and time.monotonic() < deadline:
                status, count = take.drain(subscription, size - 1)
                dropped += take.records(count)
                assert status == QUEUE_EMPTY
        assert dropped == [(gid, number + i, TOO_LARGE, size, 0) for i in (1, 2, 3)]
        publisher.publish(messages[1])
        with subscription.handle:
            while take.drain(subscription, size) != (MESSAGE_WAITING, 0) and time.monotonic() < deadline:
                time.sleep(0.01)
            assert take.waiting()[0] == messages[1]
            assert take.drain(subscription, size) == (QUEUE_EMPTY, 0)
    finally:
        probe.close()


def test_a_window_of_steps_lets_through_only_what_the_node_can_take_and_counts_the_rest():
    """A subscription given a window of (episode, steps): messages outside it are dropped before
    Python (``_drain.c`` reads their header) and handed to the node's refusal with their count
    and the last one's episode and step; those inside, and one too short to tell, reach the
    callback; every one is counted as received, and a publisher's gap in between still counts."""
    import time

    config = load_project(default_config_dir())
    probe = ProbeNode('window_test')
    try:
        diagnostics = Diagnostics(probe.node, 'window_test')
        taken, refused = [], []
        Intake(probe.node, diagnostics, limits_of(config)).subscribe(
            CavCommandArray, COMMANDS_TOPIC, taken.append, QoSProfile(depth=5), raw=True,
            window=lambda: (4, 10, 15), refuse=lambda *refusal: refused.append(refusal))
        publisher = probe.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
        assert probe.spin_until(lambda: publisher.get_subscription_count() > 0, 10)

        def commands(episode: int, step: int) -> bytes:
            return encode_commands({}, episode=episode, step=step, stamp=Time(), mode='AGGI', algorithm='gqn',
                                   policy='p')
        short = b'\x00\x01\x00\x00\xff'
        for message in (commands(4, 10), commands(3, 12), commands(4, 9), short, commands(4, 15)):
            publisher.publish(message)
        time.sleep(0.5)   # all in the queue: one pass takes them
        assert probe.spin_until(lambda: diagnostics.counters.get('received_cav_commands') == 5, 10), \
            diagnostics.counters
        assert taken == [commands(4, 10), short, commands(4, 15)]
        assert refused == [(4, 9, 2)]
        # the queue (depth 5) kept the last five of eight: the three it overwrote count as a gap
        for step in range(20, 28):
            publisher.publish(commands(4, step))
        time.sleep(0.5)
        assert probe.spin_until(lambda: diagnostics.counters.get('received_cav_commands') == 10, 10), \
            diagnostics.counters
        assert diagnostics.counters['dropped_cav_commands'] == 3
        assert refused[-1] == (4, 27, 5) and len(taken) == 3
    finally:
        probe.close()


def test_a_message_takes_the_waiting_episode_starts_unless_it_came_before_they_were_taken():
    """Before judging a message of another episode, a node takes the episode starts waiting for it
    (the start came first), except when their queue was emptied after the message was received:
    then its start, had one come, was taken then (so a flood of stale messages costs no take of
    the events each). A start still waiting is seen by a message received after it, and not by
    one received before the queue's last emptying."""
    import time

    from exit_decision.input_checks import StepGate
    from exit_decision.ros.executor import emptied_at

    config = load_project(default_config_dir())
    topic = '/events_order_test'
    probe = ProbeNode('events_order_test')
    try:
        diagnostics, gate = Diagnostics(probe.node, 'events_order_test'), StepGate(100)

        events = Intake(probe.node, diagnostics, limits_of(config)).subscribe(
            EpisodeEvent, topic, diagnostics.episode_starts(gate.announce), EVENT_QOS, raw=True)
        publisher = probe.node.create_publisher(EpisodeEvent, topic, EVENT_QOS)
        assert probe.spin_until(lambda: publisher.get_subscription_count() > 0, 10)
        publisher.publish(EpisodeEvent(episode=1))
        assert probe.spin_until(lambda: gate.episode == 1, 10)   # taken: the queue emptied
        before = emptied_at(events) - 1                          # a message received before that
        publisher.publish(EpisodeEvent(episode=2))
        time.sleep(0.3)                                          # waiting in the queue, not taken
        assert diagnostics.out_of_sequence(gate, events, 2, 0, 'states', received=before)
        assert 2 not in gate.announced, 'a message received before the emptying takes no events'
        assert not diagnostics.out_of_sequence(gate, events, 2, 0, 'states', received=time.time_ns())
        assert 2 in gate.announced, 'one received after the start was sent sees it'
    finally:
        probe.close()


def test_the_intake_counts_what_a_full_queue_overwrote_for_each_of_two_publishers():
    """Two publishers (two processes' worth: two participants) on one topic, a reader queue of 5:
    after each publisher's first message is taken, 40 more from each arrive before the node takes
    again; what the queue overwrote shows as gaps in each publisher's sequence and is counted, so
    taken + dropped = sent."""
    config = load_project(default_config_dir())
    topic, qos = '/intake_overwrite_test', QoSProfile(depth=5)
    listener, senders = ProbeNode('intake_overwrite_test'), [ProbeNode(f'overwriter_{i}') for i in range(2)]
    try:
        diagnostics = Diagnostics(listener.node, 'intake_overwrite_test')
        Intake(listener.node, diagnostics, limits_of(config)).subscribe(EpisodeEvent, topic, lambda msg: None, qos)
        publishers = [sender.node.create_publisher(EpisodeEvent, topic, QoSProfile(depth=100)) for sender in senders]
        assert listener.spin_until(lambda: all(p.get_subscription_count() > 0 for p in publishers), 10)
        message = serialize_message(EpisodeEvent(episode=1))
        for publisher in publishers:
            publisher.publish(message)
        assert listener.spin_until(lambda: diagnostics.counters.get('received_intake_overwrite_test') == 2, 10)
        for _ in range(40):
            for publisher in publishers:
                publisher.publish(message)
        for publisher in publishers:
            assert publisher.wait_for_all_acked(Duration(seconds=5))
        listener.spin_until(lambda: False, 0.5)
        counters = diagnostics.counters
        assert counters['received_intake_overwrite_test'] < 82, 'the queue overwrote some'
        assert counters['received_intake_overwrite_test'] + counters['dropped_intake_overwrite_test'] == 82, counters
    finally:
        for probe in (listener, *senders):
            probe.close()


def test_the_recorder_refuses_a_message_over_the_limit_counts_it_and_the_bag_says_so(tmp_path):
    bag = tmp_path / 'bag'
    recorder = start_node('recorder', {'bag_path': str(bag)}, tmp_path / 'recorder.log')
    probe = ProbeNode('recorder_flood_test')
    limit = limits_of(load_project(default_config_dir()))[STATES_TOPIC]
    try:
        counters = {}

        def on_diagnostics(msg: DiagnosticArray) -> None:
            counters.update({kv.key: float(kv.value) for status in msg.status if status.name == 'recorder'
                             for kv in status.values})
        probe.node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, STREAM_QOS)
        publisher = probe.node.create_publisher(VehicleStateArray, STATES_TOPIC, STREAM_QOS)
        assert probe.spin_until(lambda: publisher.get_subscription_count() > 0, 30)
        probe.spin_until(lambda: False, 0.5)
        good = encode_states([], episode=1, step=1, step_length=0.1)
        for message in (good, padded(good, limit + 1), padded(good, 6_000_000), good):
            publisher.publish(message)
        assert probe.spin_until(lambda: counters.get('received_vehicle_states') == 4, 30), counters
        assert counters['dropped_vehicle_states_too_large'] == 2 and counters['recorded_vehicle_states'] == 2
        assert stop(recorder, sig=15) == 0
    finally:
        probe.close()
        stop(recorder, sig=9)
    assert [len(raw) for topic, _, raw in read_raw(bag) if topic == STATES_TOPIC] == [len(good)] * 2
    custom = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']['custom_data']
    assert json.loads(custom[REFUSED_KEY]) == {'dropped_vehicle_states_too_large': 2}


def read_raw(bag):
    from rosbags.rosbag2 import Reader
    with Reader(bag) as reader:
        for connection, stamp, raw in reader.messages():
            yield connection.topic, stamp, raw


def test_under_a_flood_commands_keep_coming_memory_stays_bounded_and_every_drop_is_counted():
    """The default stack, synchronous, while two processes flood the states topic for a few
    seconds with messages over its limit (a few of them huge: 60,000 vehicles), at the stack's
    own state rate: no node dies (the run would stop), decisions go on during the flood, every
    node's peak memory stays under MEMORY_MB, and every subscriber counts every message as too
    large. (The bench's targets, 10x the rate and the wait's p99, are figures, not asserted.)"""
    run = bench_flood(phase_seconds=3.0, pairs=1, topics=[STATES_TOPIC], kinds=('oversized',), rate_factor=1.0,
                      huge_bytes_per_s=10e6)
    (phase,) = run.phases
    assert phase.sent > 0
    assert len(run.waits([phase.window])) > 0, 'decision steps answered during the flood'
    assert run.peak_mb and all(mb < MEMORY_MB for mb in run.peak_mb.values()), run.peak_mb
    assert run.uncounted(phase) == {node: 0.0 for node in run.subscribers[STATES_TOPIC]}, phase.counted


def test_the_waits_p99_pools_the_pairs_of_a_topic_and_kind():
    """One flood window's p99 is its few longest waits; the bench's ratio takes every flood window
    of a (topic, kind) against every window between them, not each pair alone."""
    from exit_decision.ros.stack.flood import FloodRun, Phase, report

    run = FloodRun(state_rate=100.0, subscribers={STATES_TOPIC: []})
    for pair, (flood_wait, quiet_wait) in enumerate(((0.010, 0.004), (0.004, 0.010))):
        start = 100.0 * pair
        phase = Phase(STATES_TOPIC, 'oversized', 1000.0, sent=5, rate=1000.0, window=(start, start + 10),
                      quiet=(start + 20, start + 30))
        run.phases.append(phase)
        for step in range(10):
            for at, wait in ((start + step, flood_wait), (start + 20 + step, quiet_wait)):
                key = (1, len(run.decision_steps))
                run.decision_steps[key], run.decided_at[key] = wait, at
    text, ok = report(run)
    lines = [line for line in text.splitlines() if 'decision wait p99' in line]
    assert len(lines) == 2 and all('20 steps), 10.00 ms without (20 steps), its 2 pairs pooled: 1.00x ok' in line
                                   for line in lines), text


def test_a_flood_below_its_rate_fails_the_bench_and_one_no_middleware_would_send_is_not_applicable():
    """An oversized flood of a bounded type (/clock's) cannot be sent: every message refused by the
    flooders' own middleware, none reaching the stack; the bench says so and judges nothing of
    it. A flood that did go out but below its target rate fails the run."""
    from exit_decision.ros.stack.flood import FloodRun, Phase, report

    def run_of(phase: Phase) -> FloodRun:
        run = FloodRun(state_rate=100.0, subscribers={phase.topic: []}, phases=[phase])
        for step in range(40):   # as long waits in the flood as without it
            key = (1, step)
            run.decision_steps[key], run.decided_at[key] = 0.004, (5.0 if step < 20 else 25.0) + step % 20 * 0.1
        return run
    unsent = Phase(CLOCK_TOPIC, 'oversized', 1000.0, refused=3000, window=(0.0, 10.0), quiet=(20.0, 30.0))
    text, ok = report(run_of(unsent))
    assert ok and 'not applicable' in text and 'every one of 3000' in text, text
    slow = Phase(CLOCK_TOPIC, 'stale', 1000.0, sent=9000, rate=900.0, window=(0.0, 10.0), quiet=(20.0, 30.0))
    text, ok = report(run_of(slow))
    assert not ok and '900 msg/s (0.0 MB/s) BELOW the target 1000' in text and '1.00x ok' in text, text
