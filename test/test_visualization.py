"""The scene as markers, and `exit-decision show` on a small bag: what a user looks at."""
import dataclasses
import math

import numpy as np
import pytest
from PIL import Image

from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import CavCommand
from exit_decision.visualization.layout import CLASS_COLOURS, COLLISION_COLOUR, RoadLayout
from exit_decision.visualization.markers import MarkerScene
from exit_decision.visualization.trace import FrameBuilder

from conftest import make_vehicle

STEP = 0.1


@pytest.fixture(scope='module')
def layout(project_config):
    road = project_config.scenario.road
    return RoadLayout.of(RoadGeometry.of(road), road)


def snapshot():
    """Two CAVs and one vehicle of each human class on the highway; HV3 about to leave by Exit_0."""
    return [make_vehicle('CAV_0', 'CAV', lane=1, position=60.0),
            make_vehicle('CAV_1', 'CAV', lane=2, position=90.0),
            make_vehicle('HV1_0', 'HV1', lane=0, position=120.0),
            make_vehicle('HV2_0', 'HV2', lane=1, position=40.0),
            dataclasses.replace(make_vehicle('HV3_0', 'HV3', lane=0, position=190.0, edge='Exit_0'),
                                route_target='Exit_0')]


def test_markers_of_a_snapshot_show_each_vehicle_in_its_class_colour_and_delete_departed_ones(layout):
    vehicles = snapshot()
    hv3_end = layout.ramps['Exit_0'].end
    vehicles[-1] = dataclasses.replace(vehicles[-1], position=hv3_end - 1.0)
    frames = FrameBuilder(layout, STEP, episode=3)
    frames.decide({'CAV_0': CavCommand(+1, -6.0), 'CAV_1': CavCommand(0, 2.0)}, mode='AGGP')
    frames.graph(['CAV_0', '', 'HV1_0'], np.array([[1, 0, 1], [0, 0, 0], [1, 0, 1]]))
    scene = MarkerScene(layout)
    first = scene.update(frames.add(0, vehicles))

    assert first[0].action == 'DELETEALL', 'a new episode clears what an earlier one left'
    by_ns = {}
    for marker in first[1:]:
        assert marker.action == 'ADD'
        by_ns.setdefault(marker.namespace, []).append(marker)
    boxes = {m.marker_id: m for m in by_ns['vehicles']}
    ids = {m.marker_id: m.text for m in by_ns['vehicle_ids']}
    assert len(boxes) == 5 and sorted(ids.values()) == sorted(v.vehicle_id for v in vehicles)
    for marker_id, box in boxes.items():
        vehicle = next(v for v in vehicles if v.vehicle_id == ids[marker_id])
        assert box.kind == 'CUBE' and box.colour[:3] == CLASS_COLOURS[vehicle.vehicle_class]
        assert box.scale[0] == vehicle.length
    assert len({box.colour for box in boxes.values()}) == 4, 'four classes, four colours'
    on_ramp = next(b for i, b in boxes.items() if ids[i] == 'HV3_0')
    assert on_ramp.position[1] < -10 and on_ramp.yaw < 0, 'a vehicle on Exit_0 is drawn down the ramp'
    # each CAV's command: the lane change to the left points left, braking is red, speeding up green
    arrows = {ids[m.marker_id]: m for m in by_ns['commands']}
    assert set(arrows) == {'CAV_0', 'CAV_1'} and all(a.kind == 'ARROW' for a in arrows.values())
    (x0, y0, _), (x1, y1, _) = arrows['CAV_0'].points
    assert y1 - y0 == pytest.approx(layout.lane_spacing) and x1 > x0
    assert arrows['CAV_1'].points[1][1] == pytest.approx(arrows['CAV_1'].points[0][1])
    red, green, _, _ = arrows['CAV_0'].colour
    assert red > 0.7 and green < 0.3
    red, green, _, _ = arrows['CAV_1'].colour
    assert green > red
    assert len(by_ns['graph_edges']) == 1 and len(by_ns['graph_edges'][0].points) == 2
    assert 'mode AGGP' in by_ns['status'][0].text and 'episode 3' in by_ns['status'][0].text
    assert len(by_ns['road']) == layout.lane_count + 1 + 2 * len(layout.ramps)
    assert 'collisions' not in by_ns

    # next step: HV1_0 vanished mid-road (SUMO removed it: a collision), HV3_0 reached the end of Exit_0
    second = scene.update(frames.add(1, vehicles[:2] + vehicles[3:4]))
    deleted = {(m.namespace, m.marker_id) for m in second if m.action == 'DELETE'}
    gone = {i for i, text in ids.items() if text in ('HV1_0', 'HV3_0')}
    assert {('vehicles', i) for i in gone} <= deleted and {('vehicle_ids', i) for i in gone} <= deleted
    assert ('graph_edges', 0) in deleted, 'the edge to HV1_0 went with it'
    assert not [m for m in second if m.action == 'DELETEALL']
    assert len([m for m in second if m.namespace == 'vehicles' and m.action == 'ADD']) == 3
    collisions = [m for m in second if m.namespace == 'collisions']
    assert len(collisions) == 1 and collisions[0].colour[:3] == COLLISION_COLOUR
    assert collisions[0].position[0] == pytest.approx(120.0 - 2.5), 'where HV1_0 was last'
    text = [m.text for m in second if m.namespace == 'collision_text']
    assert text == ['collision HV1_0'], 'HV3_0 arrived: no collision'


def test_markers_become_a_marker_array_in_frame_map(layout):
    from visualization_msgs.msg import Marker

    from exit_decision.ros.nodes.visualizer import marker_array

    frames = FrameBuilder(layout, STEP)
    vehicles = snapshot()
    msg = marker_array(MarkerScene(layout).update(frames.add(0, vehicles)), stamp=_stamp())
    assert msg.markers[0].action == Marker.DELETEALL
    cubes = [m for m in msg.markers if m.ns == 'vehicles']
    assert len(cubes) == 5 and all(m.type == Marker.CUBE and m.header.frame_id == 'map' for m in cubes)
    ramp = next(m for m in cubes if m.pose.position.y < -10)
    yaw = 2 * math.atan2(ramp.pose.orientation.z, ramp.pose.orientation.w)
    assert yaw == pytest.approx(math.atan2(*reversed(layout.ramps['Exit_0'].direction)))
    cav = next(m for m in cubes if m.color.b > 0.6)
    assert (cav.color.r, cav.color.g, cav.color.b) == pytest.approx(CLASS_COLOURS['CAV'])


def _stamp():
    from exit_decision.ros.messages.conversions import stamp_of
    return stamp_of(0.0)


# --- `exit-decision show` on a fixture bag ---------------------------------------------------------

def write_fixture_bag(path, layout, lane_shift=0, commands_late=0):
    """One episode of 40 steps: 5 vehicles; CAV_0 commanded left at step 10; the mode switches
    from AGGP to CONP at step 20; HV1_0 disappears mid-road at step 30 (a collision).
    ``lane_shift``: every lane index that much higher (a bag of a wider road); ``commands_late``:
    the commands logged that many steps after their states (the recorder writes in batches)."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer

    from exit_decision.graph import TrafficGraph
    from exit_decision.ros.bags.storage import DEFAULT_TOPICS, typestore
    from exit_decision.ros.topics import COMMANDS_TOPIC, GRAPH_TOPIC, STATES_TOPIC
    from exit_decision.ros.messages.conversions import commands_to_msg, graph_to_msg, stamp_of, states_to_msg

    store = typestore()
    vehicles = {}
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {topic: writer.add_connection(topic, DEFAULT_TOPICS[topic], typestore=store)
                       for topic in (STATES_TOPIC, GRAPH_TOPIC, COMMANDS_TOPIC)}
        for step in range(40):
            states = [dataclasses.replace(v, position=v.position + 20.0 * STEP * step, lane_index=lane_shift
                                          + (2 if v.vehicle_id == 'CAV_0' and step > 12 else v.lane_index))
                      for v in snapshot() if not (v.vehicle_id == 'HV1_0' and step >= 30)]
            vehicles.update({v.vehicle_id: v.vehicle_class for v in states})
            stamp = 1_000_000_000 + step * 10_000_000
            writer.write(connections[STATES_TOPIC], stamp, serialize_message(
                states_to_msg(states, episode=0, step=step, step_length=STEP)))
            n = len(states)
            graph = TrafficGraph(np.zeros((n, 3), np.float32), np.eye(n, dtype=np.uint8) | np.eye(n, k=1, dtype=np.uint8)
                                 | np.eye(n, k=-1, dtype=np.uint8), np.array([v.is_cav for v in states]),
                                 tuple(v.vehicle_id for v in states))
            writer.write(connections[GRAPH_TOPIC], stamp + 1, serialize_message(
                graph_to_msg(graph, feature_set='test', episode=0, step=step, stamp=stamp_of(step * STEP))))
            if step % 5 == 0:
                commands = {'CAV_0': CavCommand(1 if step == 10 else 0, 1.0), 'CAV_1': CavCommand(0, -2.0)}
                logged = stamp + 2 + commands_late * 10_000_000
                writer.write(connections[COMMANDS_TOPIC], logged, serialize_message(commands_to_msg(
                    commands, episode=0, step=step, stamp=stamp_of(step * STEP), mode='AGGP' if step < 20 else 'CONP',
                    algorithm='mdgqn_conditioned', policy='test')))
    return vehicles


def class_pixels(image: np.ndarray, box, colour, tolerance=12) -> int:
    left, top, right, bottom = box
    area = image[top:bottom, left:right, :3].astype(int)
    return int((np.abs(area - np.array(colour) * 255).max(axis=2) <= tolerance).sum())


@pytest.mark.parametrize('commands_late', [0, 7])
def test_show_draws_every_vehicle_of_a_bag_in_its_class_colour_and_a_clip(project_config, layout, tmp_path,
                                                                           commands_late):
    from exit_decision.ros.bags.show import show_bag

    bag = tmp_path / 'bag'
    vehicles = write_fixture_bag(bag, layout, commands_late=commands_late)
    [shown] = show_bag(bag, project_config, tmp_path / 'out', progress=False)
    diagram = shown.diagram
    assert diagram.trajectories == vehicles, 'a trajectory drawn for every vehicle of the bag, in its class'
    assert len(diagram.lines) == len(set(diagram.lines)), 'one line per vehicle in each panel, not pieces'
    assert {panel for panel, vehicle_id in diagram.lines if vehicle_id == 'CAV_0'} == {1, 2}, 'CAV_0 went left'
    assert len(diagram.lines) == len(vehicles) + 1
    assert diagram.lane_changes == 1 and diagram.collisions == 1
    assert [(round(t, 1), a, b) for t, a, b in diagram.mode_switches] == [(2.0, 'AGGP', 'CONP')], 'at its decision'
    image = np.asarray(Image.open(diagram.path).convert('RGB'))
    assert len(diagram.plot_areas) == layout.lane_count + 1
    for name, colour in CLASS_COLOURS.items():
        inside = sum(class_pixels(image, box, colour) for box in diagram.plot_areas)
        assert inside > 50, f'{name} trajectories drawn inside the panels ({inside} pixels)'
    lane_of = {'CAV': (0, 1), 'HV1': (2,), 'HV2': (1,), 'HV3': (3,)}   # panels from the top: lanes 2, 1, 0, ramps
    for name, panels in lane_of.items():
        for index, box in enumerate(diagram.plot_areas):
            present = class_pixels(image, box, CLASS_COLOURS[name]) > 20
            assert present == (index in panels), f'{name} in panel {index}: {present}'
    [clip] = shown.clips if len(shown.clips) == 1 else [c for c in shown.clips if c.suffix == '.gif']
    assert clip.suffix == '.gif'
    with Image.open(clip) as gif:
        assert gif.n_frames == 9, 'every 5th step of 40 (5x real time at 10 fps) and the last'
        gif.seek(4)
        frame = np.asarray(gif.convert('RGB'))
        assert all(class_pixels(frame, (0, 0, frame.shape[1], frame.shape[0]), c, 20) > 5
                   for c in CLASS_COLOURS.values()), 'every class on the road in the clip'


def test_show_command_writes_beside_the_bag_and_refuses_bad_input_in_one_line(layout, tmp_path, capsys):
    from exit_decision.cli import main

    bag = tmp_path / 'bag'
    write_fixture_bag(bag, layout)
    write_fixture_bag(tmp_path / 'wide', layout, lane_shift=1)
    assert main(['show', str(bag), '--start', '1.0', '--end', '2.0']) == 0
    out = capsys.readouterr().out
    assert 'episode 0: 5 vehicles, 11 steps (1.0-2.0 s)' in out
    assert (tmp_path / 'bag_show' / 'episode_0_time_space.png').is_file()
    assert (tmp_path / 'bag_show' / 'episode_0_birds_eye.gif').is_file()
    for argv, expected in [(['show', str(tmp_path / 'nope')], 'nope: no such bag'),
                           (['show', str(bag), '--episode', '4'], '--episode 4: not in'),
                           (['show', str(bag), '--start', '3', '--end', '1'], 'the window is empty'),
                           (['show', str(tmp_path / 'wide')], 'CAV_1 is in lane 3, the road of the config has 3')]:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert expected in err and len(err.splitlines()) == 1, err
    with pytest.raises(SystemExit) as exit_:
        main(['show', str(bag), '--fps', '0'])
    assert exit_.value.code == 2 and "'0': expected a number > 0" in capsys.readouterr().err


def first_markers(test, publisher, arrays) -> int:
    """Start episode 0 (as the bridge does), wait for the visualizer to subscribe, then send the
    same vehicles at steps 0, 1, ... until the markers reader is matched too and the first array
    arrives; the last step sent."""
    from exit_decision_msgs.msg import EpisodeEvent

    from exit_decision.ros.topics import EPISODE_TOPIC, EVENT_QOS
    from exit_decision.ros.messages.conversions import states_to_msg

    events = test.node.create_publisher(EpisodeEvent, EPISODE_TOPIC, EVENT_QOS)
    events.publish(EpisodeEvent(episode=0, event=EpisodeEvent.EVENT_STARTED))   # transient local: it reaches a late joiner
    assert test.spin_until(lambda: publisher.get_subscription_count() > 0, 30), 'the visualizer subscribes'
    for step in range(40):
        publisher.publish(states_to_msg(snapshot(), episode=0, step=step, step_length=STEP))
        if test.spin_until(lambda: arrays, 0.5):
            return step
    raise AssertionError('no markers')


def test_visualizer_node_publishes_the_scene_on_the_markers_topic(tmp_path):
    from exit_decision_msgs.msg import VehicleStateArray
    from visualization_msgs.msg import Marker, MarkerArray

    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.topics import MARKERS_TOPIC, STATES_TOPIC, STREAM_QOS
    from exit_decision.ros.messages.conversions import states_to_msg
    from exit_decision.ros.stack.launcher import start_node
    from ros_helpers import stop

    test = ProbeNode('visualizer_test')
    arrays = []
    test.node.create_subscription(MarkerArray, MARKERS_TOPIC, arrays.append, STREAM_QOS)
    publisher = test.node.create_publisher(VehicleStateArray, STATES_TOPIC, STREAM_QOS)
    node = start_node('visualizer', {'max_rate': 0.0}, tmp_path / 'visualizer.log')
    try:
        step = first_markers(test, publisher, arrays)
        publisher.publish(states_to_msg(snapshot()[:3], episode=0, step=step + 1, step_length=STEP))
        assert test.spin_until(lambda: any(m.action == Marker.DELETE for m in arrays[-1].markers), 10)
    finally:
        test.close()
        stop(node)
    cubes = [m for m in arrays[0].markers if m.ns == 'vehicles']
    assert len(cubes) == 5 and {m.header.frame_id for m in arrays[0].markers} == {'map'}
    deleted = [m for m in arrays[-1].markers if m.action == Marker.DELETE and m.ns == 'vehicles']
    assert len(deleted) == 2, 'HV2_0 and HV3_0 left: their boxes are deleted'


def test_visualizer_sends_the_last_frame_its_rate_limit_held_back(tmp_path):
    from exit_decision_msgs.msg import VehicleStateArray
    from visualization_msgs.msg import MarkerArray

    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.topics import MARKERS_TOPIC, STATES_TOPIC, STREAM_QOS
    from exit_decision.ros.messages.conversions import states_to_msg
    from exit_decision.ros.stack.launcher import start_node
    from ros_helpers import stop

    test = ProbeNode('visualizer_rate_test')
    arrays = []
    test.node.create_subscription(MarkerArray, MARKERS_TOPIC, arrays.append, STREAM_QOS)
    publisher = test.node.create_publisher(VehicleStateArray, STATES_TOPIC, STREAM_QOS)
    node = start_node('visualizer', {'max_rate': 0.5}, tmp_path / 'visualizer.log')   # one array per 2 s

    def boxes():
        return sum(m.ns == 'vehicles' and m.action == m.ADD for m in arrays[-1].markers)
    try:
        step = first_markers(test, publisher, arrays)
        assert boxes() == 5
        sent = len(arrays)
        for later, count in ((1, 4), (2, 3)):   # within the rate limit of the first: both held back
            publisher.publish(states_to_msg(snapshot()[:count], episode=0, step=step + later, step_length=STEP))
        assert test.spin_until(lambda: len(arrays) > sent and boxes() == 3, 20), 'the last one comes after all'
    finally:
        test.close()
        stop(node)


def test_visualizer_rejects_and_counts_states_that_cannot_follow_or_do_not_fit_and_draws_on(tmp_path):
    """A states message of another episode, one whose lane the road does not have, and one
    out of step order are each refused whole, and so are commands of another episode: the next
    good states are drawn as if they never came."""
    from builtin_interfaces.msg import Time
    from exit_decision_msgs.msg import CavCommandArray, VehicleStateArray
    from visualization_msgs.msg import MarkerArray

    from exit_decision.ros.messages.commands_cdr import encode_commands

    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.topics import COMMANDS_TOPIC, MARKERS_TOPIC, STATES_TOPIC, STREAM_QOS
    from exit_decision.ros.messages.conversions import states_to_msg
    from exit_decision.ros.stack.launcher import start_node
    from ros_helpers import stop
    from test_ros_stack import diagnostics_of

    test = ProbeNode('visualizer_reject_test')
    commands = test.node.create_publisher(CavCommandArray, COMMANDS_TOPIC, STREAM_QOS)
    arrays = []
    test.node.create_subscription(MarkerArray, MARKERS_TOPIC, arrays.append, STREAM_QOS)
    counters = diagnostics_of(test, 'visualizer')
    publisher = test.node.create_publisher(VehicleStateArray, STATES_TOPIC, STREAM_QOS)
    node = start_node('visualizer', {'max_rate': 0.0}, tmp_path / 'visualizer.log')

    def boxes():
        return sorted(m.text for m in arrays[-1].markers if m.ns == 'vehicle_ids' and m.action == m.ADD)
    try:
        step = first_markers(test, publisher, arrays)
        test.spin_until(lambda: False, 1.5)   # every array of the first steps, and the diagnostics after them
        drawn, before = len(arrays), dict(counters)
        bad_lane = [dataclasses.replace(v, lane_index=127) if v.vehicle_id == 'CAV_0' else v for v in snapshot()]
        for episode, at, vehicles in ((1000, step + 1, snapshot()[:1]), (0, step + 1, bad_lane),
                                      (0, step, snapshot()[:2])):
            publisher.publish(states_to_msg(vehicles, episode=episode, step=at, step_length=STEP))
        commands.publish(encode_commands({}, episode=1000, step=step, stamp=Time(), mode='AGGI', algorithm='gqn',
                                         policy='p'))
        publisher.publish(states_to_msg(snapshot()[:4], episode=0, step=step + 1, step_length=STEP))
        assert test.spin_until(lambda: len(arrays) > drawn, 10)
        assert test.spin_until(lambda: tuple(counters.get(key, 0) - before.get(key, 0) for key in (
            'rejected_out_of_sequence_states', 'rejected_states', 'dropped_cav_commands_out_of_sequence')) == (2, 1, 1),
            10), (before, counters)
    finally:
        test.close()
        stop(node)
    assert len(arrays) == drawn + 1, 'only the good message was drawn'
    assert boxes() == sorted(v.vehicle_id for v in snapshot()[:4])


def test_evaluate_show_draws_the_first_episodes_of_a_run_without_ros(tmp_path):
    from exit_decision.config import load_project
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.driving.fixed import sumo
    from exit_decision.evaluation.evaluate import play_episodes
    from exit_decision.visualization.episodes import ShowEpisodes
    from ros_helpers import small_config_dir

    env = ExitDecisionEnv(load_project(small_config_dir(tmp_path / 'config')), cav_driver='sumo')
    try:
        played = play_episodes(env, sumo(), [7, 8], show=ShowEpisodes(tmp_path / 'show', 1).named('sumo', 'CONI'))
        entered = sum(len(ids) for ids in env.episode_log.entered.values())
    finally:
        env.close()
    assert len(played) == 2 and entered == 12
    assert sorted(p.name for p in (tmp_path / 'show').iterdir()) == ['sumo_seed7_birds_eye.gif',
                                                                     'sumo_seed7_time_space.png']


# --- shield overrides, CAV lane changes, the bridge's collision count --------------------------------

def test_a_cav_the_shield_overrode_is_framed_until_its_next_command(layout):
    from exit_decision.shield_overrides import ShieldOverride

    frames = FrameBuilder(layout, STEP)
    scene = MarkerScene(layout)
    scene.update(frames.add(0, snapshot()))
    override = ShieldOverride(CavCommand(1, 2.0), CavCommand(0, -1.0))
    frames.shield({'CAV_0': override}, step=0)            # the overrides may come before their commands
    frames.decide({'CAV_0': CavCommand(0, -1.0), 'CAV_1': CavCommand(0, 0.5)}, 'AGGP', step=0)
    frame = frames.add(1, snapshot())
    assert frame.new_overrides == {'CAV_0': override}
    markers = scene.update(frame)
    framed = [m for m in markers if m.namespace == 'shield_overrides']
    ids = {m.marker_id: m.text for m in markers if m.namespace == 'vehicle_ids'}
    assert [ids[m.marker_id] for m in framed] == ['CAV_0'], 'only the overridden CAV'
    box = next(m for m in markers if m.namespace == 'vehicles' and ids[m.marker_id] == 'CAV_0')
    assert framed[0].scale[0] > box.scale[0] and framed[0].position[:2] == box.position[:2]
    assert [m.text for m in markers if m.namespace == 'shield_text'] == ['shield: +1 +2.0 -> +0 -1.0']
    assert frames.add(2, snapshot()).overridden == {'CAV_0': override}, 'held with the command'
    frames.decide({'CAV_0': CavCommand(0, 0.0)}, step=5)  # the next decision: not overridden
    frames.shield({'CAV_0': override}, step=0)            # a late copy of the older decision's: ignored
    later = scene.update(frames.add(6, snapshot()))
    assert not [m for m in later if m.namespace == 'shield_overrides' and m.action == 'ADD'
                and ids[m.marker_id] == 'CAV_0'], 'the next command without override clears it'
    assert ('shield_overrides', next(i for i, t in ids.items() if t == 'CAV_0')) in {
        m.key for m in later if m.action == 'DELETE'}


def write_events_and_overrides(path, layout, p_collision):
    """The fixture bag with CAV_0's command at step 10 overridden by the shield, CAV_1 released to
    SUMO at step 24 and changing lane right at step 26, and the bridge's episode end."""
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer

    from exit_decision.ros.bags.storage import DEFAULT_TOPICS, typestore
    from exit_decision.ros.topics import COMMANDS_TOPIC, EPISODE_TOPIC, OVERRIDES_TOPIC, STATES_TOPIC
    from exit_decision.ros.messages.conversions import (commands_to_msg, episode_event_to_msg, overrides_to_msg,
                                                        stamp_of, states_to_msg)
    from exit_decision.shield_overrides import ShieldOverride

    store = typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {topic: writer.add_connection(topic, DEFAULT_TOPICS[topic], typestore=store)
                       for topic in (STATES_TOPIC, COMMANDS_TOPIC, OVERRIDES_TOPIC, EPISODE_TOPIC)}
        for step in range(40):
            states = []
            for v in snapshot():
                if v.vehicle_id == 'HV1_0' and step >= 30:
                    continue
                lane = 2 if v.vehicle_id == 'CAV_0' and step > 12 else 1 if v.vehicle_id == 'CAV_1' and step > 26 \
                    else v.lane_index
                states.append(dataclasses.replace(v, position=v.position + 20.0 * STEP * step, lane_index=lane,
                                                  controlled=v.controlled and not (v.vehicle_id == 'CAV_1'
                                                                                   and step >= 24)))
            stamp = 1_000_000_000 + step * 10_000_000
            writer.write(connections[STATES_TOPIC], stamp, serialize_message(
                states_to_msg(states, episode=0, step=step, step_length=STEP)))
            if step % 5 == 0:
                commands = {'CAV_0': CavCommand(1 if step == 10 else 0, 1.0)}
                writer.write(connections[COMMANDS_TOPIC], stamp + 2, serialize_message(commands_to_msg(
                    commands, episode=0, step=step, stamp=stamp_of(step * STEP), mode='AGGP', algorithm='a',
                    policy='test')))
            if step == 15:
                overrides = {'CAV_0': ShieldOverride(CavCommand(0, 5.0), CavCommand(0, 1.0))}
                writer.write(connections[OVERRIDES_TOPIC], stamp + 3, serialize_message(overrides_to_msg(
                    overrides, episode=0, step=step, stamp=stamp_of(step * STEP))))
        writer.write(connections[EPISODE_TOPIC], 2_000_000_000, serialize_message(episode_event_to_msg(
            1, episode=0, seed=1, steps=39, time=3.9, metrics={
                'v_AVs': 20.0, 'v_s': 20.0, 'p_collision': p_collision, 'p_collision_CAV': 0.0, 'N_braking': 0,
                'braking_steps': 0, 'p_CAV': 1.0, 'p_HV2': 1.0, 'reward': 0.0})))


@pytest.mark.parametrize('p_collision', [0.5, 0.0])
def test_show_marks_overrides_every_cav_lane_change_and_trusts_the_bridges_collision_count(
        project_config, layout, tmp_path, p_collision):
    from exit_decision.ros.bags.show import show_bag

    bag = tmp_path / 'bag'
    write_events_and_overrides(bag, layout, p_collision)
    [shown] = show_bag(bag, project_config, tmp_path / 'out', progress=False)
    d = shown.diagram
    assert d.overrides == 1, 'CAV_0 overridden at step 15'
    assert (d.lane_changes, d.sumo_lane_changes) == (2, 1), "CAV_0 by command, CAV_1 by SUMO's driver"
    assert shown.trace.collisions == round(p_collision * 2)
    assert d.collisions == (1 if p_collision else 0), 'HV1_0 vanished: a crash only if the bridge counted one'
    summary = shown.summary()
    assert f'the bridge counted {round(p_collision * 2)} collision(s)' in summary and '1 shield override(s)' in summary
    image = np.asarray(Image.open(d.path).convert('RGB'))
    from exit_decision.visualization.markers import OVERRIDE_COLOUR
    assert sum(class_pixels(image, box, OVERRIDE_COLOUR[:3], 20) for box in d.plot_areas) > 10, 'override marked'


def test_show_reads_the_replay_fixture_recorded_before_overrides_had_a_topic(project_config, tmp_path):
    from pathlib import Path

    from exit_decision.ros.bags.show import show_bag

    bag = Path(__file__).parent / 'fixtures' / 'replay_bag' / 'bag'
    [shown] = show_bag(bag, project_config, tmp_path / 'out', start=0.0, end=5.0, progress=False)
    assert shown.diagram.trajectories and shown.diagram.overrides == 0


@pytest.mark.parametrize('driver', ['rule_based', 'policy'])
def test_the_cavs_found_overridden_are_those_the_shield_counted(tmp_path, driver):
    from exit_decision.config import load_project
    from exit_decision.driving.episode import play_episode
    from exit_decision.driving.fixed import GridDriver
    from exit_decision.driving.policy import policy_driver
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.model.modes import ModeWeights
    from exit_decision.model.names import GRID_ALGORITHM, default_policy_dir, policy_path
    from exit_decision.model.policy import load_controller
    from ros_helpers import small_config_dir

    config = load_project(small_config_dir(tmp_path / 'config'))
    env = ExitDecisionEnv(config)
    if driver == 'rule_based':
        choose = env.rule_based_driver().decide
    else:
        choose = policy_driver(load_controller(config, policy_path(default_policy_dir(), GRID_ALGORITHM), env.shield,
                                               env.planner), config, ModeWeights(config).mode('AGGP')).grid_decision
    decisions, totals = [], {'found': 0, 'counted': 0}

    def recorded(graph, snapshot):
        decisions.append(choose(graph, snapshot))
        return decisions[-1]

    def check(step, info, terminated, truncated):
        decision = decisions[-1]
        assert len(step.overrides) == decision.overridden
        for vehicle_id, override in step.overrides.items():
            assert override.applied == env.actions.command(decision.actions[vehicle_id]) == step.commands[vehicle_id]
            assert override.preferred != override.applied
        totals['found'] += len(step.overrides)
        totals['counted'] += decision.overridden

    try:
        play_episode(env, GridDriver(driver, env.actions, recorded), 7, check)
    finally:
        env.close()
    assert totals['counted'] > 0, 'the episode has overrides to find'


def test_the_option_a_cav_holds_is_written_under_its_id_and_goes_with_it(layout):
    from exit_decision.agents.options import CavOption, Option
    vehicles = [dataclasses.replace(v, controlled=v.is_cav) for v in snapshot()]
    frames = FrameBuilder(layout, STEP)
    frames.decide({'CAV_0': CavCommand(0, 1.0), 'CAV_1': CavCommand(0, 0.0)}, mode='CONP')
    frames.options({'CAV_0': CavOption(Option('route', 'calm'), 4, 0.0), 'CAV_1': CavOption(Option('left', 'close'), 6, 0.0)})
    scene = MarkerScene(layout)
    labels = sorted(m.text for m in scene.update(frames.add(0, vehicles)) if m.namespace == 'vehicle_ids')
    assert labels == ['CAV_0\nroute calm', 'CAV_1\nleft close', 'HV1_0', 'HV2_0', 'HV3_0']
    gone = frames.add(1, vehicles[1:])   # CAV_0 left the road
    assert gone.options == {'CAV_1': 'left close'}
