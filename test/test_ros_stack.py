"""Integration tests of the ROS 2 stack: nodes in their own processes, on loopback only."""
import dataclasses
import math
import os
import signal
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from exit_decision_msgs.msg import (CavCommand, CavCommandArray, EpisodeEvent, TrafficGraph as GraphMsg,
                                    VehicleState, VehicleStateArray)
from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters
from rclpy.parameter import parameter_value_to_python
from rosbags.rosbag2 import Reader

from exit_decision.config import load_project
from exit_decision.graph import GraphBuilder
from exit_decision.ros.bags.storage import read_messages
from exit_decision.ros.probe import ProbeNode
from exit_decision.ros.topics import (COMMANDS_QOS, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC, EVENT_QOS,
                                      GRAPH_TOPIC, OPTIONS_TOPIC, OVERRIDES_TOPIC, STATES_QOS, STATES_TOPIC, STREAM_QOS)
from exit_decision.ros.messages.commands_cdr import encode_commands
from exit_decision.ros.messages.conversions import graph_from_msg, states_from_msg
from exit_decision.ros.stack.launcher import run_stack, start_node
from exit_decision.ros.bags.replay import replay_decisions
from exit_decision.ros.stack.node_table import plan
from exit_decision import traffic
from exit_decision.scenario.geometry import RoadGeometry

from ros_helpers import random_policies, small_config_dir, stop
from test_training import TINY


@pytest.fixture(scope='module')
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp('ros')
    config_dir = small_config_dir(root / 'config')
    return {'root': root, 'config_dir': config_dir, 'policies': random_policies(config_dir, root / 'policies')}


def diagnostics_of(test: ProbeNode, name: str) -> dict:
    latest = {}

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == name:
                latest.update({kv.key: float(kv.value) for kv in status.values})
    test.node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, on_diagnostics, STREAM_QOS)
    return latest


def set_parameter(test: ProbeNode, node_name: str, name: str, value):
    client = test.node.create_client(SetParameters, f'/{node_name}/set_parameters')
    assert test.spin_until(client.service_is_ready, 30), f'{node_name} parameter service not up'
    # the service is discoverable as soon as the node exists, but answered only once it spins
    # (after loading its policies): allow for a slow first start on a fresh machine
    result = test.set_parameter(client, name, value, timeout=60)
    assert result is not None, f'{node_name} did not answer set_parameters within 60 s'
    return result


def test_stack_runs_switches_mode_records_and_replays(setup):
    root, config_dir, policies = setup['root'], setup['config_dir'], setup['policies']
    bag = root / 'bag'
    run = run_stack(mode='AGGP', algorithm='mdgqn_conditioned', episodes=1, seed=10_000, bag_path=bag, log_dir=root / 'logs',
                    switch_to='CONP', switch_at_step=100, config_dir=str(config_dir), policy_dir=str(policies),
                    timeout=300)
    assert run.mode_switch.endswith('accepted'), run.mode_switch
    assert len(run.episodes) == 1 and run.episodes[0]['steps'] > 100
    assert all(code in (0, -2) for code in run.return_codes.values()), run.return_codes
    topics = {}
    for topic, _, _, msg in read_messages(bag):
        topics.setdefault(topic, []).append(msg)
    steps = int(run.episodes[0]['steps'])
    assert len(topics[STATES_TOPIC]) == steps + 1, 'every state of the episode is in the bag'
    config = load_project(config_dir)
    interval, road = config.env.decision_interval, config.scenario.road
    assert [m.step for m in topics[GRAPH_TOPIC]] == list(range(0, steps + 1, interval)), 'graphs of decision steps only'
    # each as the environment of training and evaluation makes it: its builder fed the decision steps
    builder = GraphBuilder(config.graph, RoadGeometry.of(road).road_length, road.highway_speed_limit, road.lane_count)
    as_trained = {m.step: builder.build(states_from_msg(m, road.names.sections)) for m in topics[STATES_TOPIC]
                  if m.step % interval == 0}
    for m in topics[GRAPH_TOPIC]:
        graph, expected = graph_from_msg(m), as_trained[m.step]
        assert graph.vehicle_ids == expected.vehicle_ids and np.array_equal(graph.features, expected.features) \
            and np.array_equal(graph.adjacency, expected.adjacency), f'graph of step {m.step}'
    modes = [m.mode for m in topics[COMMANDS_TOPIC]]
    assert modes[0] == 'AGGP' and modes[-1] == 'CONP' and modes.count('CONP') < len(modes)
    assert len(topics[COMMANDS_TOPIC]) == steps // 5 + 1, 'a decision on every state of a 5th step, none missed'
    sent = {(m.step, c.vehicle_id): (c.lane_change, c.acceleration) for m in topics[COMMANDS_TOPIC] for c in m.commands}
    overridden = [(m.step, o) for m in topics.get(OVERRIDES_TOPIC, []) for o in m.overrides]
    assert overridden, 'the shield overrode the random policy: the CAVs are recorded'
    assert all(sent[(step, o.vehicle_id)] == (o.applied_lane_change, o.applied_acceleration)
               and (o.preferred_lane_change, o.preferred_acceleration) != sent[(step, o.vehicle_id)]
               for step, o in overridden), 'each override names the command sent instead of the one preferred'
    report = replay_decisions(bag, load_project(config_dir), policies)
    assert report.commands > 0 and report.matching == report.commands and report.missing_inputs == 0
    other = replay_decisions(bag, load_project(config_dir), policies, mode='AGGI')
    assert other.matching < other.commands, 'the one conditioned network decides differently at another mode'
    per_mode = replay_decisions(bag, load_project(config_dir), policies, algorithm='mdgqn')
    assert per_mode.matching < per_mode.commands, 'a per-mode policy is another network'


def test_a_policy_over_options_drives_publishes_its_options_ends_them_at_a_switch_and_replays(setup):
    """The decision node runs a conditioned policy over options: every decision's options are
    recorded beside its commands, a mode switch ends every option held, and the replay decides
    the same commands and options again (issue 28)."""
    root, config_dir, policies = setup['root'], setup['config_dir'], setup['policies']
    bag = root / 'options_bag'
    run = run_stack(mode='AGGP', algorithm='mdgqn_options_conditioned', episodes=1, seed=10_002, bag_path=bag,
                    log_dir=root / 'options_logs', switch_to='CONP', switch_at_step=100, config_dir=str(config_dir),
                    policy_dir=str(policies), timeout=300, visualizer=False)
    assert run.mode_switch.endswith('accepted') and len(run.episodes) == 1, run.mode_switch
    topics = {}
    for topic, _, _, msg in read_messages(bag, {COMMANDS_TOPIC, OPTIONS_TOPIC}):
        topics.setdefault(topic, []).append(msg)
    commands = {m.step: m for m in topics[COMMANDS_TOPIC]}
    options = {m.step: m for m in topics[OPTIONS_TOPIC]}
    assert set(options) == set(commands) and any(m.options for m in options.values())
    assert all({o.vehicle_id for o in options[s].options} == {c.vehicle_id for c in commands[s].commands}
               for s in commands), 'every commanded CAV holds an option'
    config = load_project(config_dir)
    hold = config.env.options.hold_time
    switched = min(s for s, m in commands.items() if m.mode == 'CONP')
    assert all(o.started == switched * config.scenario.step_length for o in options[switched].options), \
        'every option begins anew at the first decision after the switch'
    held_on = [o for m in options.values() for o in m.options if m.step * config.scenario.step_length - o.started > 0]
    assert held_on and all(m.step * config.scenario.step_length - o.started < hold + 1e-6
                           for m in options.values() for o in m.options), 'options are held, at most hold_time'
    report = replay_decisions(bag, config, policies)
    assert report.reproduced and report.options == sum(len(m.options) for m in options.values()), report.summary(3)


def test_the_stack_drives_with_another_method_as_published_and_the_replay_agrees(setup):
    """A paper-002 grid-state DQN as published (its own encoder, the bare shield, no lane
    planner), trained for an episode, drives the stack through `stack --algorithm`'s path; every
    command it sent is what the offline controller decides on the recorded states."""
    from exit_decision.learning.trainer import Trainer

    root, config_dir = setup['root'], setup['config_dir']
    config = load_project(config_dir, overrides=[TINY])
    policies = root / 'other_policies'
    trained = Trainer(config, 'dqn_published', 'CONP', 0, root / 'dqn_run').run(episodes=1, progress=False)
    (policies / 'dqn_published_CONP').mkdir(parents=True)
    (policies / 'dqn_published_CONP' / 'policy.pt').write_bytes(trained.read_bytes())
    bag = root / 'dqn_bag'
    run = run_stack(mode='CONP', modes=['CONP'], algorithm='dqn_published', episodes=1, seed=10_001, bag_path=bag,
                    log_dir=root / 'dqn_logs', switch_to=None, config_dir=str(config_dir), policy_dir=str(policies),
                    timeout=300, visualizer=False)
    assert len(run.episodes) == 1 and all(code in (0, -2) for code in run.return_codes.values()), run.return_codes
    commands = [msg for topic, _, _, msg in read_messages(bag, {COMMANDS_TOPIC})]
    assert len(commands) == int(run.episodes[0]['steps']) // 5 + 1
    assert {m.algorithm for m in commands} == {'dqn_published'} and any(m.commands for m in commands)
    report = replay_decisions(bag, load_project(config_dir), policies)
    assert report.commands > 0 and report.matching == report.commands, report.differences[:3]


def test_mode_parameter_refuses_unknown_values_with_a_reason(setup):
    process = start_node('decision_node', {'config_dir': setup['config_dir'], 'policy_dir': setup['policies'],
                                           'mode': 'AGGI'}, setup['root'] / 'decision_param.log')
    test = ProbeNode('param_test')
    try:
        refused = set_parameter(test, 'decision_node', 'mode', 'FAST')
        assert not refused.successful and "unknown mode 'FAST'" in refused.reason and 'CONP' in refused.reason
        assert set_parameter(test, 'decision_node', 'mode', 'CONI').successful
        refused = set_parameter(test, 'decision_node', 'algorithm', 'dqn')
        assert not refused.successful and "unknown algorithm 'dqn'" in refused.reason
    finally:
        test.close()
        stop(process)


def get_parameters(test: ProbeNode, node_name: str, names: list[str]) -> list:
    """What `ros2 param get` shows: the node's get_parameters service."""
    client = test.node.create_client(GetParameters, f'/{node_name}/get_parameters')
    assert test.spin_until(client.service_is_ready, 30)
    response = test.call(client, GetParameters.Request(names=names), timeout=60)
    assert response is not None, f'{node_name} did not answer get_parameters within 60 s'
    return [parameter_value_to_python(v) for v in response.values]


def read_only_of_every_parameter(test: ProbeNode, node_name: str) -> dict[str, bool]:
    """Every parameter the node declares (`ros2 param list`) -> whether it is read-only
    (`ros2 param describe`)."""
    clients = {kind: test.node.create_client(kind, f'/{node_name}/{name}')
               for kind, name in ((ListParameters, 'list_parameters'), (DescribeParameters, 'describe_parameters'))}
    assert all(test.spin_until(client.service_is_ready, 30) for client in clients.values())
    listed = test.call(clients[ListParameters], ListParameters.Request(), timeout=60)
    assert listed is not None, f'{node_name} did not answer list_parameters within 60 s'
    described = test.call(clients[DescribeParameters], DescribeParameters.Request(names=listed.result.names),
                          timeout=60)
    assert described is not None, f'{node_name} did not answer describe_parameters within 60 s'
    return {descriptor.name: descriptor.read_only for descriptor in described.descriptors}


def test_conditioned_policy_takes_any_reward_weights_and_keeps_mode_consistent(setup):
    process = start_node('decision_node', {'config_dir': setup['config_dir'], 'policy_dir': setup['policies'],
                                           'algorithm': 'mdgqn_conditioned', 'algorithms': ['mdgqn_conditioned', 'gqn'],
                                           'mode': 'AGGI'},
                         setup['root'] / 'decision_weights.log')
    test = ProbeNode('weights_test')
    try:
        assert set_parameter(test, 'decision_node', 'mode', 'CONP').successful
        mode, weights = get_parameters(test, 'decision_node', ['mode', 'reward_weights'])
        assert mode == 'CONP' and list(weights) == pytest.approx([0.2, 0.2, 0.25, 0.35, 0.4, 0.6])
        point = [0.3, 0.3, 0.2, 0.2, 0.5, 0.5]
        assert set_parameter(test, 'decision_node', 'reward_weights', point).successful
        mode, weights = get_parameters(test, 'decision_node', ['mode', 'reward_weights'])
        assert mode == 'custom' and list(weights) == pytest.approx(point)
        assert set_parameter(test, 'decision_node', 'reward_weights', [0.25, 0.35, 0.15, 0.25, 0.6, 0.4]).successful
        assert get_parameters(test, 'decision_node', ['mode']) == ['AGGI'], 'the weights of a mode name it'
        refused = set_parameter(test, 'decision_node', 'reward_weights', [0.5, 0.5, 0.5, 0.5, 0.5, 0.5])
        assert not refused.successful and 'must sum to 1' in refused.reason
        refused = set_parameter(test, 'decision_node', 'reward_weights', ['a', 'b'])
        assert not refused.successful, 'a wrong type is refused'
        assert get_parameters(test, 'decision_node', ['mode']) == ['AGGI'], 'and the node lives on'
        refused = set_parameter(test, 'decision_node', 'algorithm', 'gqn')
        assert refused.successful, 'per-mode gqn has a policy for AGGI'
        assert set_parameter(test, 'decision_node', 'mode', 'CONP').successful, 'and one for CONP'
        refused = set_parameter(test, 'decision_node', 'reward_weights', point)
        assert not refused.successful and 'conditioned' in refused.reason
    finally:
        test.close()
        stop(process)


def test_the_start_algorithm_defaults_to_the_last_of_the_algorithms_loaded(setup):
    process = start_node('decision_node', {'config_dir': setup['config_dir'], 'policy_dir': setup['policies'],
                                           'algorithms': ['gqn'], 'modes': ['AGGI']},
                         setup['root'] / 'decision_algorithms.log')
    test = ProbeNode('algorithms_test')
    try:
        assert get_parameters(test, 'decision_node', ['algorithm', 'mode']) == ['gqn', 'AGGI']
        assert process.poll() is None
    finally:
        test.close()
        stop(process)


def test_missing_policy_fails_at_start_naming_the_path(setup, tmp_path):
    process = start_node('decision_node', {'config_dir': setup['config_dir'], 'policy_dir': str(tmp_path)},
                         tmp_path / 'decision.log')
    assert process.wait(60) == 1
    assert f'{tmp_path}/mdgqn_conditioned/policy.pt: no such policy file' in (tmp_path / 'decision.log').read_text()


def start_episode(test: ProbeNode, episode: int):
    """Play the bridge's part: an EVENT_STARTED (transient local, so a node started later gets it)."""
    events = test.node.create_publisher(EpisodeEvent, EPISODE_TOPIC, EVENT_QOS)
    events.publish(EpisodeEvent(episode=episode, event=EpisodeEvent.EVENT_STARTED))
    return events


def test_malformed_messages_are_rejected_and_counted(setup):
    root = setup['root']
    decision = start_node('decision_node', {'config_dir': setup['config_dir'], 'policy_dir': setup['policies']},
                          root / 'decision_bad.log')
    test = ProbeNode('malformed_test')
    try:
        counters = diagnostics_of(test, 'decision_node')
        graphs = test.node.create_publisher(GraphMsg, GRAPH_TOPIC, STREAM_QOS)
        states = test.node.create_publisher(VehicleStateArray, STATES_TOPIC, STREAM_QOS)
        start_episode(test, 0)
        assert test.spin_until(lambda: graphs.get_subscription_count() and states.get_subscription_count(), 30)
        test.spin_until(lambda: False, 0.5)   # let the node's side of the connections match too
        wrong_n = GraphMsg(episode=0, step=0, num_nodes=3, num_features=20, vehicle_ids=['', '', ''])
        wrong_n.features = np.zeros(60, np.float32)
        wrong_n.adjacency = np.zeros(9, np.uint8).tobytes()
        wrong_n.cav_mask = np.zeros(3, np.uint8).tobytes()
        states.publish(VehicleStateArray(episode=0, step=0, step_length=0.1))
        graphs.publish(wrong_n)
        assert test.spin_until(lambda: counters.get('rejected_graphs', 0) >= 1, 20), counters
        answered = []
        test.node.create_subscription(CavCommandArray, COMMANDS_TOPIC, answered.append, STREAM_QOS)
        for step in (5, 0):                        # the graph of step 0 comes after the one of step 5
            empty = GraphMsg(episode=0, step=step, num_nodes=60, num_features=20, vehicle_ids=[''] * 60)
            empty.features = np.zeros(60 * 20, np.float32)
            empty.adjacency = np.zeros(3600, np.uint8).tobytes()
            empty.cav_mask = np.zeros(60, np.uint8).tobytes()
            states.publish(VehicleStateArray(episode=0, step=step, step_length=0.1))
            graphs.publish(empty)
        assert test.spin_until(lambda: counters.get('rejected_out_of_sequence_graphs', 0) >= 1, 20), counters
        assert [m.step for m in answered] == [5], 'the valid graph is answered, the late one is not'
        assert decision.poll() is None, 'the node is still running'
    finally:
        test.close()
        stop(decision)


def test_bridge_survives_a_decision_node_that_stops_and_restarts(setup):
    root, config_dir, policies = setup['root'], setup['config_dir'], setup['policies']
    common = {'config_dir': config_dir}
    graph = start_node('graph_builder', common, root / 'graph_restart.log')
    decision_params = {**common, 'policy_dir': policies}
    decision = start_node('decision_node', decision_params, root / 'decision_restart1.log')
    test = ProbeNode('restart_test')
    latest = {'step': -1}
    test.node.create_subscription(VehicleStateArray, STATES_TOPIC,
                                  lambda m: latest.update(step=m.step), STREAM_QOS)
    commands = []
    test.node.create_subscription(CavCommandArray, COMMANDS_TOPIC, commands.append, STREAM_QOS)
    # episodes 0 (until stopped): however long the restart takes, there is an episode to decide
    # in (a fixed-length episode raced it); the restarted node joins the running episode through
    # its transient-local EVENT_STARTED, or the next one's. The bridge starts once graph
    # builder, decision node and this probe listen.
    bridge = start_node('sumo_bridge', {**common, 'episodes': 0, 'command_timeout': 1.0, 'wait_for_subscribers': 3},
                        root / 'bridge_restart.log')
    try:
        assert test.spin_until(lambda: latest['step'] >= 50, 60)
        stop(decision, sig=9)                              # the decision node dies
        stopped_at = latest['step']
        assert test.spin_until(lambda: latest['step'] >= stopped_at + 20, 60), 'the bridge goes on alone'
        decision = start_node('decision_node', decision_params, root / 'decision_restart2.log')
        answered = len(commands)
        assert test.spin_until(lambda: len(commands) > answered + 5, 120), 'decisions resume after the restart'
        assert bridge.poll() is None and stop(bridge) == 0
        assert 'no commands for step' in (root / 'bridge_restart.log').read_text()
    finally:
        test.close()
        for process in (bridge, decision, graph):
            stop(process)


def test_a_bridge_started_alone_waits_for_its_peers_saying_what_it_waits_for(setup):
    """As with `ros2 run`: no step and no giving up (no startup_timeout by default), a line every
    few seconds naming what is missing; once a listener and a commands publisher come, it steps."""
    log = setup['root'] / 'bridge_alone.log'
    bridge = start_node('sumo_bridge', {'config_dir': setup['config_dir'], 'episodes': 1}, log)
    test = ProbeNode('alone_test')
    states = []
    try:
        assert test.spin_until(lambda: log.read_text().count('waiting for') >= 2, 60), log.read_text()
        text = log.read_text()
        assert f'1 more subscriber(s) of {STATES_TOPIC}' in text and f'a publisher of {COMMANDS_TOPIC}' in text, text
        assert bridge.poll() is None and 'starting anyway' not in text
        test.node.create_subscription(VehicleStateArray, STATES_TOPIC, states.append, STREAM_QOS)
        test.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
        assert test.spin_until(lambda: states, 60), 'with its peers there, it steps'
    finally:
        test.close()
        stop(bridge)


def test_recorder_loses_nothing_on_sigterm(setup, tmp_path):
    bag = tmp_path / 'bag'
    recorder = start_node('recorder', {'bag_path': str(bag)}, tmp_path / 'recorder.log')
    test = ProbeNode('recorder_test')
    try:
        publisher = test.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
        assert test.spin_until(lambda: publisher.get_subscription_count() > 0, 30)
        test.spin_until(lambda: False, 0.5)   # matched here first: let the recorder's side match too
        counters = diagnostics_of(test, 'recorder')
        for step in range(200):
            publisher.publish(CavCommandArray(step=step, mode='AGGI'))
        for step in (0, 5, 10, 30, 35):                  # a decision node away for steps 15-25
            publisher.publish(CavCommandArray(episode=1, step=step, mode='AGGI'))
        assert test.spin_until(lambda: counters.get('messages') == 205, 30), counters
        assert counters['gaps_cav_commands'] == 1 and counters['missing_steps_cav_commands'] == 3, counters
        assert stop(recorder, sig=15) == 0
    finally:
        test.close()
        stop(recorder, sig=9)
    steps = [msg.step for topic, _, _, msg in read_messages(bag) if topic == COMMANDS_TOPIC]
    assert steps == list(range(200)) + [0, 5, 10, 30, 35]
    assert f'{COMMANDS_TOPIC}: 3 step(s) in 1 gap(s)' in (tmp_path / 'recorder.log').read_text()


def test_the_recorders_memory_stays_flat_however_many_messages_it_records(setup, tmp_path):
    """The recorder once grew 93 -> 457 MB in 18 minutes. Over 60000 more states messages (of 12
    vehicles, about 1 KB each: 60 MB if it kept them), once its buffers are warm, its resident
    memory grows by less than 8 MB: room for its 1 MB chunk, its depth-1000 queue and the
    allocator's slack."""
    from exit_decision.ros.stack.bench import resident_mb

    bag = tmp_path / 'bag'
    recorder = start_node('recorder', {'bag_path': str(bag)}, tmp_path / 'recorder.log')
    test = ProbeNode('recorder_memory_test')
    vehicles = [VehicleState(vehicle_id=f'HV1_{i}', edge_id='Highway_0', position=10.0 * i, speed=20.0,
                             route_target='Highway_2') for i in range(12)]
    try:
        counters = diagnostics_of(test, 'recorder')
        publisher = test.node.create_publisher(VehicleStateArray, STATES_TOPIC, STATES_QOS)
        assert test.spin_until(lambda: publisher.get_subscription_count() > 0, 30)
        test.spin_until(lambda: False, 0.5)
        sent = 0

        def record(messages: int) -> None:
            """Publish ``messages`` at about 10000 a second (a burst the recorder's depth-1000 queue
            takes), then wait until the recorder has them (its counter, on /diagnostics once a second)."""
            nonlocal sent
            for _ in range(messages // 1000):
                for _ in range(1000):
                    publisher.publish(VehicleStateArray(episode=sent // 1000, step=sent % 1000, step_length=0.1,
                                                        vehicles=vehicles))
                    sent += 1
                test.spin_until(lambda: False, 0.1)
            assert test.spin_until(lambda: counters.get('messages', 0) >= sent, 30), (sent, counters)

        record(10_000)
        status = Path(f'/proc/{recorder.pid}/status')
        warm = resident_mb(status.read_text())
        record(60_000)
        grown = resident_mb(status.read_text()) - warm
        assert grown < 8.0, f'the recorder grew by {grown:.1f} MB over 60000 messages (from {warm:.0f} MB)'
        assert stop(recorder, sig=15) == 0
    finally:
        test.close()
        stop(recorder, sig=9)
    with Reader(bag) as reader:
        assert sum(c.msgcount for c in reader.connections if c.topic == STATES_TOPIC) == 70_000


def test_a_recorder_killed_with_sigkill_leaves_a_bag_repair_recovers(setup, tmp_path, capsys):
    from exit_decision.cli import main
    from exit_decision.ros.nodes.recorder import FLUSH_PERIOD

    bag = tmp_path / 'bag'
    recorder = start_node('recorder', {'bag_path': str(bag)}, tmp_path / 'recorder.log')
    test = ProbeNode('recorder_kill_test')
    try:
        counters = diagnostics_of(test, 'recorder')
        publisher = test.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
        assert test.spin_until(lambda: publisher.get_subscription_count() > 0, 30)
        test.spin_until(lambda: False, 0.5)
        for step in range(200):
            publisher.publish(CavCommandArray(step=step, mode='AGGI'))
        assert test.spin_until(lambda: counters.get('messages') == 200, 30), counters
        test.spin_until(lambda: False, 2 * FLUSH_PERIOD + 1)   # the recorder's flush timer has run since
        stop(recorder, sig=9)
    finally:
        test.close()
        stop(recorder, sig=9)
    assert main(['replay', str(bag)]) == 2
    assert f'`exit-decision bag repair {bag}` recovers it' in capsys.readouterr().err
    assert main(['bag', 'repair', str(bag)]) == 0
    assert 'recovered 200 messages' in capsys.readouterr().out
    steps = [msg.step for topic, _, _, msg in read_messages(bag) if topic == COMMANDS_TOPIC]
    assert steps == list(range(200)), 'everything received a flush period before the kill'


def test_bridge_rejects_commands_it_cannot_apply_and_goes_on(setup):
    root = setup['root']
    test = ProbeNode('bad_commands_test')
    counters = diagnostics_of(test, 'sumo_bridge')
    seen = []
    test.node.create_subscription(VehicleStateArray, STATES_TOPIC, seen.append, STREAM_QOS)
    publisher = test.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
    # the bridge waits for this test's subscription and publisher, then for the commands of step 0
    bridge = start_node('sumo_bridge', {'config_dir': setup['config_dir'], 'episodes': 1, 'command_timeout': 10.0},
                        root / 'bridge_bad.log')
    try:
        assert test.spin_until(lambda: seen, 30)
        assert seen[0].step == 0
        publisher.publish(CavCommandArray(episode=0, step=0, commands=[
            CavCommand(vehicle_id='CAV_999', lane_change=0, acceleration=1.0)]))
        assert test.spin_until(lambda: counters.get('rejected_commands', 0) >= 1, 20), counters
        assert test.spin_until(lambda: seen[-1].step == 5, 20), 'the bridge steps on to the next decision'
        raw = encode_commands({'CAV_999': traffic.CavCommand(0, 1.0)}, episode=0, step=5,
                              stamp=seen[-1].header.stamp, mode='AGGI', algorithm='test', policy='test')
        publisher.publish(raw[:-8])                 # bytes that are no message: rejected whole, counted
        for acceleration in (math.nan, 3e38):      # the first is rejected whole, the bridge waits on
            publisher.publish(CavCommandArray(episode=0, step=5, commands=[
                CavCommand(vehicle_id='CAV_999', lane_change=0, acceleration=acceleration)]))
        assert test.spin_until(lambda: seen[-1].step > 5, 20), 'the finite one is taken'
        assert test.spin_until(lambda: counters.get('clamped_commands', 0) == 1, 5), counters
        assert counters['rejected_command_messages'] == 2 and counters.get('command_timeouts', 0) == 0, counters
        assert bridge.poll() is None
    finally:
        test.close()
        stop(bridge)


def test_player_republishes_a_bag_with_its_clock(tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rclpy.serialization import serialize_message
    from rosgraph_msgs.msg import Clock

    from exit_decision.ros.bags.storage import typestore
    from exit_decision.ros.topics import CLOCK_QOS, CLOCK_TOPIC
    from exit_decision.ros.messages.conversions import stamp_of

    bag = tmp_path / 'bag'
    store = typestore()
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        commands = writer.add_connection(COMMANDS_TOPIC, 'exit_decision_msgs/msg/CavCommandArray', typestore=store)
        clock = writer.add_connection(CLOCK_TOPIC, 'rosgraph_msgs/msg/Clock', typestore=store)
        for step in range(20):
            stamp = 1_000_000_000 + step * 100_000_000
            writer.write(clock, stamp, serialize_message(Clock(clock=stamp_of(step * 0.1))))
            writer.write(commands, stamp, serialize_message(CavCommandArray(step=step, mode='CONI')))
    test = ProbeNode('player_test')
    received, clocks = [], []
    test.node.create_subscription(CavCommandArray, COMMANDS_TOPIC, received.append, STREAM_QOS)
    test.node.create_subscription(Clock, CLOCK_TOPIC, clocks.append, CLOCK_QOS)
    player = start_node('player', {'bag_path': str(bag), 'rate': 5.0, 'wait_for_subscribers': 1},
                        tmp_path / 'player.log')
    try:
        assert test.spin_until(lambda: len(received) == 20, 30), len(received)
        assert [m.step for m in received] == list(range(20)) and received[0].mode == 'CONI'
        assert test.spin_until(lambda: clocks and clocks[-1].clock == stamp_of(1.9), 10), 'the clock ends at 1.9 s'
        assert player.wait(30) == 0
    finally:
        test.close()
        stop(player)


def bad_messages(latest: VehicleStateArray) -> list:
    """The fuzzer's findings (issue 12), aimed at what the stack is doing now: states for the
    next step with a bad field or sequence number, commands with a bad step or value, episode
    starts no bridge sent."""
    from rclpy.serialization import serialize_message

    from exit_decision.ros.messages.conversions import states_to_msg
    from conftest import make_vehicle

    episode, step = latest.episode, latest.step
    vehicles = states_from_msg(latest, ('Highway_0', 'Highway_1', 'Highway_2')) or [make_vehicle('HV1_0', position=20.0)]
    # bad fields on a decision step the gates accept as next (the second after this one's: within
    # their gap of two decision steps, still ahead of the stack when this process lags it by up to
    # a decision interval), so the field checks, not the sequence, refuse them
    states = [states_to_msg([dataclasses.replace(vehicles[0], **change), *vehicles[1:]], episode=episode,
                            step=step - step % 5 + 10, step_length=0.1, frame_id='fuzz')
              for change in ({'lane_index': 127}, {'lane_index': -128}, {'lane_index': 3}, {'lane_index': -1},
                             {'speed': math.nan}, {'position': 3e38})]
    states[-1].vehicles[0].vehicle_class = 9                  # no such class
    states += [states_to_msg(vehicles, episode=episode + 1000, step=step + 1, step_length=0.1, frame_id='fuzz'),
               states_to_msg(vehicles, episode=episode, step=2**32 - 1, step_length=0.1, frame_id='fuzz')]
    # bytes no rclpy publisher sends (the nodes take the states raw): a vehicle id without its NUL
    # (read to its length it would be another id), and a message too short for its header
    unterminated = bytearray(serialize_message(states_to_msg(vehicles, episode=episode, step=step - step % 5 + 10,
                                                             step_length=0.1, frame_id='fuzz')))
    name = vehicles[0].vehicle_id.encode()
    unterminated[unterminated.index(name + b'\0') + len(name)] = ord('7')
    states += [bytes(unterminated), b'\x00\x01\x00\x00\x00\x00']
    cav = next((v.vehicle_id for v in vehicles if v.controlled), 'CAV_0')
    commands = [CavCommandArray(episode=episode, step=2**32 - 1, algorithm='fuzz',
                                commands=[CavCommand(vehicle_id=cav, acceleration=1.0)]),
                CavCommandArray(episode=episode + 1000, step=step, algorithm='fuzz'),
                CavCommandArray(episode=episode, step=step - step % 5, algorithm='fuzz',
                                commands=[CavCommand(vehicle_id=cav, acceleration=math.nan)]),
                CavCommandArray(episode=episode, step=step - step % 5, algorithm='fuzz',
                                commands=[CavCommand(vehicle_id=cav, lane_change=7, acceleration=1.0)])]
    # an episode no message follows (not the +1000 of the states above: a forged start together
    # with its episode's first states is what a new bridge sends), and the episode running again
    events = [EpisodeEvent(episode=episode + 2000, event=EpisodeEvent.EVENT_STARTED, seed=-1),
              EpisodeEvent(episode=episode, event=EpisodeEvent.EVENT_STARTED, seed=-1)]
    return states + commands + events


FLOOD_RATE = 1000   # [msg/s] bad messages sent while the stack runs: the rate that starved the commands (issue 12)


def run_synchronous_episode(setup, name: str, flood: bool, deciding=('graph_builder', 'decision_node')
                            ) -> tuple[list, dict, dict]:
    """Graph builder, decision node (``deciding``: as two processes, or composed in one) and a
    synchronous bridge for one episode (seed 10000), with or without the flood of bad messages;
    its end event, the nodes' counters and the commands the decision node sent, per step."""
    root, config_dir = setup['root'], setup['config_dir']
    test = ProbeNode(f'{name}_test')
    counters = {node: diagnostics_of(test, node) for node in ('sumo_bridge', 'graph_builder', 'decision_node')}
    latest, ended, decided = [], [], {}
    test.node.create_subscription(VehicleStateArray, STATES_TOPIC,
                                  lambda m: latest.append(m) if m.header.frame_id != 'fuzz' else None, STREAM_QOS)
    test.node.create_subscription(EpisodeEvent, EPISODE_TOPIC,
                                  lambda m: ended.append(m) if m.event == EpisodeEvent.EVENT_ENDED else None,
                                  EVENT_QOS)

    def on_commands(msg: CavCommandArray) -> None:
        if msg.algorithm != 'fuzz':
            decided[msg.step] = [(c.vehicle_id, c.lane_change, c.acceleration) for c in msg.commands]
    test.node.create_subscription(CavCommandArray, COMMANDS_TOPIC, on_commands, COMMANDS_QOS)   # 1000: its own flood too
    states = test.node.create_publisher(VehicleStateArray, STATES_TOPIC, STREAM_QOS)
    commands = test.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
    events = test.node.create_publisher(EpisodeEvent, EPISODE_TOPIC, EVENT_QOS)
    nodes = [start_node(node, {'config_dir': config_dir, **({} if node == 'graph_builder' else
                                                            {'policy_dir': setup['policies']})},
                        root / f'{node}_{name}.log') for node in deciding]
    listeners = len(deciding) + 1   # each process listens to the states once (composed too), and this test
    nodes.append(start_node('sumo_bridge', {'config_dir': config_dir, 'episodes': 1,
                                            'wait_for_subscribers': listeners}, root / f'bridge_{name}.log'))
    try:
        assert test.spin_until(lambda: latest, 90), 'the stack starts'
        sent, started = 0, time.monotonic()
        while not ended and time.monotonic() - started < 150:
            if flood:
                batch = bad_messages(latest[-1])
                for _ in range(min(len(batch), int((time.monotonic() - started) * FLOOD_RATE) - sent)):
                    msg = batch[sent % len(batch)]
                    (states if isinstance(msg, (VehicleStateArray, bytes)) else
                     events if isinstance(msg, EpisodeEvent) else commands).publish(msg)
                    sent += 1
            test.executor.spin_once(timeout_sec=0.002)
        assert ended, 'the episode ends'
        test.spin_until(lambda: False, 1.5)                   # the last diagnostics
        assert all(process.poll() is None for process in nodes[:-1]), 'graph builder and decision node live'
        assert nodes[-1].wait(30) == 0
    finally:
        test.close()
        for process in nodes:
            stop(process)
    return ended, counters, decided


@pytest.fixture(scope='module')
def clean_episode(setup) -> tuple[list, dict, dict]:
    return run_synchronous_episode(setup, 'clean', flood=False)


@pytest.mark.parametrize('deciding', [('graph_builder', 'decision_node'), ('graph_and_decision',)],
                         ids=['alone', 'composed'])
def test_bad_input_and_a_flood_are_rejected_counted_and_poison_nothing(setup, clean_episode, deciding):
    """The issue's bad messages, and a flood of them (FLOOD_RATE msg/s, over half on the states
    topic, the rest on the commands and episode-events topics), sent to a running synchronous
    stack, the graph builder and the decision node as two processes or composed in one (the
    stack's default): every node lives, counts what it rejected, and decides every decision step
    exactly as the two processes do without them, with no command timeout."""
    clean_end, _, clean = clean_episode
    ended, counters, decided = run_synchronous_episode(setup, f'fuzz_{len(deciding)}', flood=True, deciding=deciding)
    steps, interval = ended[0].steps, load_project(setup['config_dir']).env.decision_interval
    bridge, graph, decision = (counters[n] for n in ('sumo_bridge', 'graph_builder', 'decision_node'))
    assert bridge.get('command_timeouts', 0) == 0, f'every decision step answered in time: {counters}'
    # a command is judged by its step first (a flood of stale ones costs a header's read each): the
    # bad fields of those that arrive while the bridge waits for their step are counted as such
    # (exactly: test_bridge_rejects_commands_it_cannot_apply_and_goes_on), the others as stale
    assert bridge['rejected_stale_commands'] > 0, bridge
    assert graph['graphs'] == steps // interval + 1, 'a graph of every decision step of the bridge'
    assert graph['rejected_states'] > 0 and graph['rejected_out_of_sequence_states'] > 0, graph
    if 'decision_node' in deciding:   # alone it checks the states itself; composed it takes the graph builder's
        assert decision['rejected_states'] > 0 and decision['rejected_out_of_sequence_states'] > 0, decision
    assert clean_end[0].steps == steps and sorted(clean) == list(range(0, steps + 1, interval)) and any(
        clean.values()), 'the clean run decided every decision step'
    assert decided == clean, 'the same commands on every decision step as in the run without bad messages'


@pytest.mark.parametrize('node, parameters, expected', [
    ('sumo_bridge', {'timing': 'fast'}, "parameter timing: 'fast' is not allowed; allowed: synchronous | realtime"),
    ('sumo_bridge', {'command_timeout': 0.0}, 'parameter command_timeout: 0.0 is not allowed; allowed: a number in'),
    ('decision_node', {'mode': 3}, 'parameter mode: 3 is not allowed; allowed: AGGI | AGGP | CONI | CONP'),
    ('decision_node', {'mode': 'XX'}, "parameter mode: 'XX' is not allowed; allowed: AGGI | AGGP | CONI | CONP"),
    ('graph_and_decision', {'decision_node:mode': 'XX'}, "parameter mode: 'XX' is not allowed; allowed: AGGI"),
    ('graph_builder', {'thread_priority': 150}, 'parameter thread_priority: 150 is not allowed; allowed: an integer in 0..99'),
    ('visualizer', {'cpu_affinity': [4096]}, 'parameter cpu_affinity: [4096] is not allowed; allowed: a non-empty list '
                                             'of the cores this process may use'),
    ('sumo_bridge', {'cpu_affinity': 0}, 'parameter cpu_affinity: 0 is not allowed; allowed: a non-empty list'),
    ('recorder', {'cpu_affinity': []}, 'parameter cpu_affinity: [] is not allowed; allowed: a non-empty list'),
    ('player', {}, 'parameter bag_path: not given'),
    ('player', {'bag_path': '/nonexistent/bag'}, 'parameter bag_path: /nonexistent/bag: no such bag'),
    ('player', {'bag_path': 'CORRUPT'}, 'not a readable bag'),
    ('recorder', {'bag_path': 'CORRUPT'}, 'exists already; allowed: a directory that does not exist yet'),
])
def test_a_bad_start_up_value_gives_one_line_and_exit_code_1(setup, tmp_path, node, parameters, expected):
    if parameters.get('bag_path') == 'CORRUPT':
        (tmp_path / 'bag').mkdir()
        (tmp_path / 'bag' / 'metadata.yaml').write_text('rosbag2_bagfile_information: [not, a, bag')
        parameters = {'bag_path': str(tmp_path / 'bag')}
    if node == 'recorder':
        parameters['config_dir'] = setup['config_dir']
    elif node != 'player':
        parameters = {'config_dir': setup['config_dir'], 'policy_dir': setup['policies'], **parameters}
        if node == 'sumo_bridge':
            del parameters['policy_dir']
    log = tmp_path / 'node.log'
    assert start_node(node, parameters, log).wait(60) == 1
    text = log.read_text()
    assert expected in text and len(text.strip().splitlines()) == 1, text


def may_run_realtime(priority: int) -> bool:
    """Can a process started from here take SCHED_FIFO at ``priority``? (Tried: root in a
    container may lack CAP_SYS_NICE.)"""
    from exit_decision.ros.stack.realtime import refusal
    return refusal(priority) is None


def without_realtime_rights():
    """Lower the rtprio limit of a child to 0 (its preexec_fn); a root child also loses
    CAP_SYS_NICE through ``setpriv`` (the command prefix returned)."""
    import resource
    import shutil
    if os.geteuid() == 0 and not shutil.which('setpriv'):
        pytest.skip('root without setpriv: cannot start a process without real-time rights')
    prefix = ['setpriv', '--bounding-set', '-sys_nice', '--inh-caps', '-sys_nice'] if os.geteuid() == 0 else []
    return prefix, lambda: resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))


def test_a_thread_priority_without_the_right_to_it_gives_one_line_and_a_failing_exit(setup, tmp_path):
    """The node (exit code 1), and the command line before it starts anything (usage error, 2)."""
    import subprocess
    import sys
    from exit_decision.ros.stack.launcher import executable, ros_args
    prefix, drop_rights = without_realtime_rights()
    log = tmp_path / 'node.log'
    with open(log, 'w') as out:
        process = subprocess.Popen(prefix + executable('graph_builder') + ros_args(
            {'config_dir': str(setup['config_dir']), 'thread_priority': 10}), stdout=out,
            stderr=subprocess.STDOUT, preexec_fn=drop_rights)
        try:
            assert process.wait(60) == 1
        finally:
            stop(process)
    text = log.read_text()
    assert 'parameter thread_priority: 10 needs real-time scheduling rights' in text, text
    assert len(text.strip().splitlines()) == 1, text
    for command in (['stack', '--episodes', '1', '--bag', str(tmp_path / 'bag')], ['bench', 'ros', '--steps', '10']):
        result = subprocess.run(prefix + [sys.executable, '-m', 'exit_decision', *command, '--thread-priority', '10'],
                                capture_output=True, text=True, preexec_fn=drop_rights, timeout=120)
        assert result.returncode == 2 and not (tmp_path / 'bag').exists(), (command, result.stderr)
        assert result.stderr.strip().splitlines() == [result.stderr.strip()] and \
            '--thread-priority 10 needs real-time scheduling rights' in result.stderr, result.stderr


@pytest.mark.skipif(not may_run_realtime(1), reason='no right to SCHED_FIFO here')
def test_one_process_takes_one_thread_priority_for_both_its_nodes(setup, tmp_path):
    """graph_and_decision runs both nodes' threads under one scheduling: priorities that differ
    between its nodes are refused in one line."""
    log = tmp_path / 'node.log'
    process = start_node('graph_and_decision', {'config_dir': setup['config_dir'], 'policy_dir': setup['policies'],
                                                'decision_node:thread_priority': 1}, log)
    assert process.wait(60) == 1
    text = log.read_text()
    assert len(text.strip().splitlines()) == 1 and 'parameter thread_priority:' in text and 'differ' in text, text


def cores_of_every_thread(pid: int) -> dict[int, str]:
    return {int(tid): next(line.split()[1] for line in open(f'/proc/{pid}/task/{tid}/status')
                           if line.startswith('Cpus_allowed_list'))
            for tid in os.listdir(f'/proc/{pid}/task')}


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason='one core: nothing to pin apart')
def test_cpu_affinity_pins_every_thread_of_the_decision_node(setup, tmp_path):
    """Those the middleware starts once its policies are loaded (its subscriptions) too; and the
    composed process refuses cores that differ between its two nodes, in one line."""
    last = max(os.sched_getaffinity(0))
    process = start_node('decision_node', {'config_dir': str(setup['config_dir']), 'policy_dir': str(setup['policies']),
                                           'cpu_affinity': [last]}, tmp_path / 'node.log')
    test = ProbeNode('affinity_test')
    try:
        assert test.spin_until(lambda: test.node.count_publishers(COMMANDS_TOPIC) > 0, 60), 'policies loaded'
        cores = cores_of_every_thread(process.pid)
        assert len(cores) > 3 and set(cores.values()) == {str(last)}, cores
        assert list(get_parameters(test, 'decision_node', ['cpu_affinity'])[0]) == [last]
    finally:
        test.close()
        stop(process)
    log = tmp_path / 'composed.log'
    composed = start_node('graph_and_decision', {'config_dir': setup['config_dir'], 'policy_dir': setup['policies'],
                                                 'decision_node:cpu_affinity': [last]}, log)
    try:
        assert composed.wait(60) == 1
    finally:
        stop(composed)
    text = log.read_text()
    assert len(text.strip().splitlines()) == 1 and 'parameter cpu_affinity:' in text and 'differ' in text, text


def test_thread_priority_runs_every_thread_of_the_decision_node_real_time(setup, tmp_path):
    """Those the middleware starts once its policies are loaded (its subscriptions) too."""
    if not may_run_realtime(10):
        pytest.skip('this user may not use real-time scheduling')
    process = start_node('decision_node', {'config_dir': str(setup['config_dir']), 'policy_dir': str(setup['policies']),
                                           'thread_priority': 10}, tmp_path / 'node.log')
    test = ProbeNode('priority_test')
    try:
        assert test.spin_until(lambda: test.node.count_publishers(COMMANDS_TOPIC) > 0, 60), 'policies loaded'
        policies = {int(tid): os.sched_getscheduler(int(tid)) for tid in os.listdir(f'/proc/{process.pid}/task')}
        assert len(policies) > 3 and set(policies.values()) == {os.SCHED_FIFO}, policies
        assert os.sched_getparam(process.pid).sched_priority == 10
    finally:
        test.close()
        stop(process)


@pytest.mark.parametrize('node, parameters, fixed, live, also_live', [
    ('sumo_bridge', {'startup_timeout': 600.0, 'wait_for_subscribers': 5},
     {'seed': 7, 'startup_timeout': 1.0, 'wait_for_subscribers': 0, 'timing': 'realtime'},
     {'command_timeout': 2.5, 'realtime_factor': 4.0, 'episodes': 3}, set()),
    ('visualizer', {}, {'config_dir': '/tmp', 'cpu_affinity': [0]}, {'max_rate': 5.0}, set()),
    ('recorder', {'bag_path': 'BAG'}, {'bag_path': '/tmp/other', 'topics': ['/clock']}, {}, set()),
    ('graph_builder', {}, {'config_dir': '/tmp', 'thread_priority': 5}, {}, set()),
    ('decision_node', {'policy_dir': 'POLICIES'},
     {'policy_dir': '/tmp', 'modes': ['CONP'], 'algorithms': ['gqn'], 'config_dir': '/tmp'}, {'mode': 'CONP'},
     {'algorithm', 'reward_weights'}),   # with the mode, each changes the others (tests of their own above)
    ('player', {'bag_path': 'PLAYED', 'rate': 0.01},
     {'bag_path': '/tmp', 'wait_for_subscribers': 2, 'cpu_affinity': [0]}, {'rate': 0.02, 'loop': True}, set()),   # rate and loop while playing: test_a_looped_bag_is_decided_again_and_the_player_answers_while_playing
])
def test_parameters_read_at_start_only_are_read_only_the_others_apply(setup, tmp_path, node, parameters, fixed, live,
                                                                      also_live):
    """Through the set_parameters service (`ros2 param set`): a parameter a node uses only at
    start refuses a new value instead of ignoring it; one it follows takes it. Every parameter
    the node declares is one or the other: read-only, or listed here as live (``also_live``:
    set in tests of their own), so a new one read only at start cannot go unnoticed."""
    parameters = {**({} if node == 'player' else {'config_dir': setup['config_dir']}), **parameters}
    if parameters.get('bag_path') == 'BAG':
        parameters['bag_path'] = str(tmp_path / 'bag')
    if parameters.get('bag_path') == 'PLAYED':
        write_episode_bag(tmp_path / 'bag', setup['config_dir'], with_graphs=False)
        parameters['bag_path'] = str(tmp_path / 'bag')
    if parameters.get('policy_dir') == 'POLICIES':
        parameters['policy_dir'] = str(setup['policies'])
    process = start_node(node, parameters, tmp_path / 'node.log')
    test = ProbeNode('read_only_test')
    try:
        for name, value in fixed.items():
            result = set_parameter(test, node, name, value)
            assert not result.successful and 'read-only' in result.reason, (name, result.reason)
        for name, value in live.items():
            assert set_parameter(test, node, name, value).successful, name
        if live:
            assert get_parameters(test, node, list(live)) == list(live.values()), 'and takes it'
        read_only = read_only_of_every_parameter(test, node)
        assert set(fixed) <= {name for name, fixed_ in read_only.items() if fixed_}
        assert {name for name, fixed_ in read_only.items() if not fixed_} == set(live) | also_live | {'use_sim_time'}, \
            'every parameter is read-only or one of those the node follows (rclpy follows use_sim_time)'
        assert process.poll() is None
    finally:
        test.close()
        stop(process)


def test_the_bridges_live_parameters_change_what_it_does_at_once(setup, tmp_path):
    """``realtime_factor`` changes the pace of the next steps and ``episodes`` (set below the
    episodes run so far) ends the run after the episode that is running: set through
    set_parameters, not just stored; a realtime bridge that cannot keep up with its factor
    still answers."""
    bridge = start_node('sumo_bridge', {'config_dir': setup['config_dir'], 'timing': 'realtime', 'cav_driver': 'sumo',
                                        'realtime_factor': 1.0, 'episodes': 0, 'wait_for_subscribers': 1},
                        tmp_path / 'bridge.log')
    test = ProbeNode('live_parameters_test')
    arrivals, ended = [], []
    test.node.create_subscription(VehicleStateArray, STATES_TOPIC, lambda _: arrivals.append(time.monotonic()),
                                  STREAM_QOS)
    test.node.create_subscription(EpisodeEvent, EPISODE_TOPIC, lambda m: ended.append(m.episode)
                                  if m.event == EpisodeEvent.EVENT_ENDED else None, EVENT_QOS)

    def steps_per_second(seconds: float) -> float:
        start = len(arrivals)
        test.spin_until(lambda: False, seconds)
        return (len(arrivals) - start) / seconds
    try:
        assert test.spin_until(lambda: len(arrivals) > 5, 60), 'the bridge steps'
        slow = steps_per_second(2.0)
        assert set_parameter(test, 'sumo_bridge', 'realtime_factor', 20.0).successful
        test.spin_until(lambda: False, 0.3)
        fast = steps_per_second(2.0)
        assert 5 < slow < 15 and fast > 5 * slow, (slow, fast)   # 10 steps/s at 1x (0.1 s steps)
        assert set_parameter(test, 'sumo_bridge', 'realtime_factor', 1000.0).successful   # more than it can do
        test.spin_until(lambda: False, 1.0)
        assert set_parameter(test, 'sumo_bridge', 'episodes', 1).successful, 'answered while behind its schedule'
        assert bridge.wait(30) == 0, 'it ended after the episode that was running (with episodes 0, never)'
        test.spin_until(lambda: False, 1.0)
    finally:
        test.close()
        stop(bridge)
    assert ended == list(range(len(ended))) and 'all episodes done' in (tmp_path / 'bridge.log').read_text()


def test_a_realtime_bridge_applies_the_decision_nodes_commands(setup, tmp_path):
    """In realtime timing (what `ros2 launch ... timing:=realtime` runs) the bridge steps on the
    clock and applies the commands the decision node sends for the steps it published (its
    window: after the last accepted, up to the newest published): over one episode, commands
    applied and none refused as stale."""
    config_dir = setup['config_dir']
    test = ProbeNode('realtime_commands_test')
    counters = diagnostics_of(test, 'sumo_bridge')
    ended = []
    test.node.create_subscription(EpisodeEvent, EPISODE_TOPIC, lambda m: ended.append(m)
                                  if m.event == EpisodeEvent.EVENT_ENDED else None, EVENT_QOS)
    nodes = [start_node('graph_and_decision', {'config_dir': config_dir, 'policy_dir': setup['policies']},
                        tmp_path / 'graph_and_decision.log'),
             start_node('sumo_bridge', {'config_dir': config_dir, 'timing': 'realtime', 'realtime_factor': 20.0,
                                        'episodes': 1, 'wait_for_subscribers': 1}, tmp_path / 'bridge.log')]
    try:
        assert test.spin_until(lambda: ended, 180), 'the episode ends'
        assert nodes[1].wait(30) == 0
        test.spin_until(lambda: False, 1.0)
    finally:
        test.close()
        for process in nodes:
            stop(process)
    assert counters.get('applied_commands', 0) > 0 and counters.get('received_cav_commands', 0) > 0, counters
    assert counters.get('rejected_stale_commands', 0) == 0, counters


def test_a_new_command_timeout_applies_from_the_next_step(setup, tmp_path):
    """A synchronous bridge whose commands never come waits a ``command_timeout`` at each decision
    step: 2 s, then, set through set_parameters while it waits, 0.05 s from the next one on."""
    interval = load_project(setup['config_dir']).env.decision_interval
    bridge = start_node('sumo_bridge', {'config_dir': setup['config_dir'], 'episodes': 1, 'command_timeout': 2.0,
                                        'wait_for_subscribers': 1}, tmp_path / 'bridge.log')
    test = ProbeNode('command_timeout_test')
    test.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)   # the bridge waits for one; none sent
    decision_steps = []   # arrival times of the states of decision steps, each followed by the bridge's wait
    test.node.create_subscription(VehicleStateArray, STATES_TOPIC, lambda m: decision_steps.append(time.monotonic())
                                  if m.step % interval == 0 else None, STREAM_QOS)
    try:
        assert test.spin_until(lambda: decision_steps, 60), 'the bridge steps'
        test.spin_until(lambda: False, 1.0)
        assert len(decision_steps) == 1, 'the next decision step comes after the 2 s timeout'
        assert set_parameter(test, 'sumo_bridge', 'command_timeout', 0.05).successful
        assert test.spin_until(lambda: len(decision_steps) >= 12, 10), len(decision_steps)
        assert decision_steps[1] - decision_steps[0] > 1.5, 'the wait under way kept its 2 s'
        gaps = np.diff(decision_steps[-10:])
        assert np.median(gaps) < 0.5, f'decision steps every {np.median(gaps):.2f} s after the change'
    finally:
        test.close()
        stop(bridge)


def test_messages_a_stalled_node_never_took_are_counted_as_dropped_on_their_topic(setup, tmp_path):
    """A graph builder stopped (SIGSTOP) while 1500 states are sent with a resend history of
    100: the ones overwritten before it could take them show as ``dropped_vehicle_states``, and
    every message sent is either taken or counted lost, never both. (Decision steps only: the
    others are not even read, so they are neither refused nor counted.)"""
    node = start_node('graph_builder', {'config_dir': setup['config_dir']}, tmp_path / 'graph_builder.log')
    test = ProbeNode('drops_test')
    counters = diagnostics_of(test, 'graph_builder')
    publisher = test.node.create_publisher(VehicleStateArray, STATES_TOPIC, STREAM_QOS)
    try:
        assert test.spin_until(lambda: publisher.get_subscription_count() > 0, 60), 'the graph builder subscribes'
        publisher.publish(VehicleStateArray(episode=0, step=0))
        assert test.spin_until(lambda: counters.get('rejected_out_of_sequence_states', 0) >= 1, 30), counters
        os.kill(node.pid, signal.SIGSTOP)
        try:
            for step in range(5, 7505, 5):
                publisher.publish(VehicleStateArray(episode=0, step=step))
        finally:
            os.kill(node.pid, signal.SIGCONT)
        test.spin_until(lambda: False, 2.0)
        publisher.publish(VehicleStateArray(episode=0, step=7505))   # shows the gap before it, if the last were lost
        # taken (and refused: no episode has started) or counted lost
        assert test.spin_until(lambda: counters.get('rejected_out_of_sequence_states', 0) + counters.get(
            'dropped_vehicle_states', 0) == 1502, 30), counters
        assert counters['dropped_vehicle_states'] > 0, counters
    finally:
        test.close()
        stop(node)


def write_episode_bag(bag, config_dir, steps: int = 40, with_graphs: bool = True) -> int:
    """A bag of one synchronous episode's first ``steps`` steps as the stack records it: the
    bridge's EVENT_STARTED, then the states of each step and (``with_graphs``) the graph of each
    decision step, 0.1 s apart. Its decision steps."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer

    from exit_decision.env import ExitDecisionEnv
    from exit_decision.ros.bags.storage import typestore
    from exit_decision.ros.messages.conversions import episode_event_to_msg, graph_to_msg, states_to_msg

    config = load_project(config_dir)
    road = config.scenario.road
    builder = GraphBuilder(config.graph, RoadGeometry.of(road).road_length, road.highway_speed_limit, road.lane_count)
    env = ExitDecisionEnv(config)
    store = typestore()
    try:
        env.reset(seed=10_000)
        result = env.sim.state
        with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            def connection(topic, name):
                return writer.add_connection(topic, f'exit_decision_msgs/msg/{name}', typestore=store)
            events, states = connection(EPISODE_TOPIC, 'EpisodeEvent'), connection(STATES_TOPIC, 'VehicleStateArray')
            graphs = connection(GRAPH_TOPIC, 'TrafficGraph') if with_graphs else None
            writer.write(events, 999_999_999, serialize_message(episode_event_to_msg(
                EpisodeEvent.EVENT_STARTED, episode=0, seed=10_000, steps=0, time=0.0)))
            for step in range(steps):
                stamp = 1_000_000_000 + step * 100_000_000
                msg = states_to_msg(result.vehicles, episode=0, step=result.step, step_length=0.1)
                writer.write(states, stamp, serialize_message(msg))
                if with_graphs and result.step % config.env.decision_interval == 0:
                    writer.write(graphs, stamp, serialize_message(graph_to_msg(
                        builder.build(result.vehicles), feature_set=config.graph.feature_set, episode=0,
                        step=result.step, stamp=msg.header.stamp)))
                result, _ = env.simulate_step(None)
    finally:
        env.close()
    return len(range(0, steps, config.env.decision_interval))


@pytest.mark.parametrize('deciding', ['decision_node', 'graph_and_decision'])
def test_a_looped_bag_is_decided_again_and_the_player_answers_while_playing(setup, tmp_path, deciding):
    """The decision node decides every pass of a looped bag (the player sends the episode's
    start on each pass), alone (graphs from the bag) or composed with its graph builder (which
    hands it the starts and the graphs it builds from the bag's states); while playing, the
    player takes a new rate and stops looping on request."""
    bag = tmp_path / 'bag'
    decisions = write_episode_bag(bag, setup['config_dir'], with_graphs=deciding == 'decision_node')
    decision = start_node(deciding, {'config_dir': setup['config_dir'], 'policy_dir': setup['policies']},
                          tmp_path / 'decision.log')
    test = ProbeNode('loop_test')
    commands = []
    test.node.create_subscription(CavCommandArray, COMMANDS_TOPIC, commands.append, STREAM_QOS)
    player = None
    try:
        assert test.spin_until(lambda: test.node.count_publishers(COMMANDS_TOPIC) > 0, 60)
        test.spin_until(lambda: False, 0.5)   # let the decision node's side of the connection match
        # at rate 0.02 a pass of the bag (4 s) takes 200 s: two passes in 120 s need the new rate
        player = start_node('player', {'bag_path': str(bag), 'rate': 0.02, 'loop': True, 'wait_for_subscribers': 1},
                            tmp_path / 'player.log')
        assert test.spin_until(lambda: commands, 60), 'the first pass is decided'
        assert set_parameter(test, 'player', 'rate', 20.0).successful
        assert test.spin_until(lambda: len(commands) >= 2 * decisions + 1, 120), len(commands)
        assert set_parameter(test, 'player', 'loop', False).successful
        assert player.wait(120) == 0, 'the pass running ends the loop'
        test.spin_until(lambda: False, 1.0)
        steps = [m.step for m in commands]
        assert steps[:2 * decisions] == list(range(0, 5 * decisions, 5)) * 2, 'every pass decided again, in order'
        assert decision.poll() is None
    finally:
        test.close()
        for process in (player, decision):
            if process is not None:
                stop(process)


def test_bench_ros_prints_speed_latency_cpu_and_memory_of_the_default_stack():
    """The benchmark command is what the speed targets are measured with: it runs and says
    what it measured (a short run; its figures are not judged here)."""
    from exit_decision.ros.stack.bench import bench_ros
    from exit_decision.ros.stack import cpu_affinity
    before = os.sched_getaffinity(0)
    text = bench_ros('', '', 100, 0)
    assert os.sched_getaffinity(0) == before, 'the benchmark leaves its caller on the cores it had'
    split = cpu_affinity.split(cpu_affinity.usable())
    where = f'decision path on cores {split[0]}, onlookers on {split[1]}, ' if split else 'no core split, '
    assert f'normal scheduling, {where}100 steps' in text, text
    for figure in ('real-time factor', 'states -> commands latency, the bridge\'s own wait from publishing the '
                   'states to the commands accepted (its last', 'from its receive stamps (late when its cores are '
                   'busy): median', 'from the publishers\' source stamps (states written -> commands written): median',
                   'CPU per step [ms]: ', 'resident memory [MB] at the first command -> after the steps: '):
        assert figure in text, (figure, text)
    for line in ('CPU per step', 'resident memory', 'cores of their threads'):
        assert all(name in next(row for row in text.splitlines() if line in row) for name, _ in plan({})), text
    if split:   # every thread of every process where the split puts it, the observer with the onlookers
        import re
        from exit_decision.ros.stack.node_table import NODES
        row = next(row for row in text.splitlines() if 'cores of their threads' in row)
        printed = {name: [int(core) for core in cores.split(', ')] for name, cores in re.findall(r'(\w+) \[([\d, ]+)\]', row)}
        path, onlookers = split
        assert printed == {'observer': onlookers, **{node.executable: path if node.decision_path else onlookers
                                                     for node in NODES}}, text


def test_the_waiter_serves_what_is_ready_and_follows_entities_made_and_destroyed():
    """The nodes' wait (executor.Waiter) keeps its wait set between passes: a subscription's queue,
    a triggered guard condition, a timer; one entity destroyed and another made (the same
    counts), then one more (other counts): each pass waits on what the node has then. rclpy's
    executor, which the Waiter calls for timers and services, is held off until the timer, so
    the messages are the Waiter's own doing."""
    from std_msgs.msg import String
    test = ProbeNode('waiter_test')
    executor, test.waiter.executor = test.waiter.executor, SimpleNamespace(spin_once=lambda timeout_sec: None)
    try:
        node, got, guarded, fired = test.node, [], [], []
        first = node.create_subscription(String, '/waiter_test/a', lambda msg: got.append(('a', msg.data)), STREAM_QOS)
        publisher = node.create_publisher(String, '/waiter_test/a', STREAM_QOS)
        assert test.spin_until(lambda: first.get_publisher_count() == 1, 10)
        for text in ('1', '2', '3'):
            publisher.publish(String(data=text))
        assert test.spin_until(lambda: len(got) == 3, 5) and got == [('a', '1'), ('a', '2'), ('a', '3')]
        guard = node.create_guard_condition(lambda: guarded.append(True))
        guard.trigger()
        assert test.spin_until(lambda: guarded, 5)
        node.destroy_subscription(first)   # and a new one: the same counts, another entity
        node.create_subscription(String, '/waiter_test/b', lambda msg: got.append(('b', msg.data)), STREAM_QOS)
        other = node.create_publisher(String, '/waiter_test/b', STREAM_QOS)
        assert test.spin_until(lambda: other.get_subscription_count() == 1, 10)
        other.publish(String(data='4'))
        publisher.publish(String(data='lost'))   # nobody subscribes to a any more
        assert test.spin_until(lambda: got[-1] == ('b', '4'), 5)
        test.waiter.executor = executor
        node.create_timer(0.01, lambda: fired.append(True))   # one entity more
        assert test.spin_until(lambda: len(fired) >= 3, 5)
        assert ('a', 'lost') not in got and guarded == [True]
    finally:
        test.close()
