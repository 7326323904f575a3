"""Input checks against the scenario (ROS-free): what the nodes reject, clamp and follow."""
import dataclasses
import math

import numpy as np
import pytest

from conftest import make_vehicle
from exit_decision.env import ExitDecisionEnv
from exit_decision.graph import GraphBuilder, GraphInputError
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import CavCommand, vehicle_id_of
from exit_decision.input_checks import MAX_ANNOUNCED, CommandLimits, InputError, StateLimits, StepGate


@pytest.fixture(scope='module')
def limits(project_config):
    return StateLimits.of(project_config, RoadGeometry.of(project_config.scenario.road))


def test_every_state_of_real_episodes_passes(project_config, limits):
    """The checks reject garbage, never what the simulation produces (policy and SUMO driven CAVs)."""
    rng = np.random.default_rng(0)
    for driver in ('policy', 'sumo'):
        env = ExitDecisionEnv(project_config, cav_driver=driver)
        try:
            env.reset(seed=3)
            result = env.sim.state
            while not (result.terminated or result.truncated):
                limits.check(result.vehicles, step=result.step, step_length=project_config.scenario.step_length)
                commands = {v.vehicle_id: CavCommand(int(rng.integers(-1, 2)), float(rng.uniform(-8, 5)))
                            for v in result.vehicles if v.controlled} if result.step % 5 == 0 else None
                result, _ = env.simulate_step(commands)
        finally:
            env.close()


@pytest.mark.parametrize('change, field', [
    ({'lane_index': 127}, 'lane_index'), ({'lane_index': -128}, 'lane_index'),
    ({'lane_index': 3}, 'lane_index'), ({'lane_index': -1}, 'lane_index'),
    ({'lane_index': 1, 'edge_id': 'Exit_1'}, 'lane_index'), ({'edge_id': 'Highway_9'}, 'edge_id'),
    ({'speed': math.nan}, 'speed'), ({'speed': -1.0}, 'speed'), ({'speed': 3e38}, 'speed'),
    ({'position': math.inf}, 'position'), ({'position': -5.0}, 'position'), ({'position': 1e6}, 'position'),
    ({'acceleration': -3e38}, 'acceleration'), ({'acceleration': math.nan}, 'acceleration'),
    ({'lateral_offset': 40.0}, 'lateral_offset'), ({'length': 0.0}, 'length'),
    ({'lane_speed_limit': math.inf}, 'lane_speed_limit'), ({'intention': 5}, 'intention'),
    ({'vehicle_class': 'TRUCK'}, 'vehicle_class'), ({'vehicle_id': 'HV1_999'}, 'vehicle_id'),
    ({'vehicle_id': 'CAV_1'}, 'vehicle_id'), ({'vehicle_id': ''}, 'vehicle_id'),
    ({'route_target': 'Mars'}, 'route_target'), ({'controlled': True}, 'controlled'),
])
def test_a_bad_field_is_named(limits, change, field):
    good = make_vehicle('HV1_1', lane=1, position=100.0)
    limits.check([good])
    with pytest.raises(InputError, match=field):
        limits.check([make_vehicle('HV1_0', position=50.0), dataclasses.replace(good, **change)])


def test_message_level_checks(limits, project_config):
    vehicles = [make_vehicle('CAV_0', 'CAV', position=30.0), make_vehicle('CAV_0', 'CAV', position=60.0)]
    with pytest.raises(InputError, match='twice'):
        limits.check(vehicles)
    with pytest.raises(InputError, match='step 4294967295'):
        limits.check([], step=2**32 - 1)
    with pytest.raises(InputError, match='step_length'):
        limits.check([], step=0, step_length=0.5)


def test_vehicle_ids_name_their_class_and_a_serial_below_its_count(limits):
    last = limits.class_counts['CAV'] - 1
    limits.check_vehicle(make_vehicle(vehicle_id_of('CAV', last), 'CAV'))
    for bad in ('CAV_', 'CAV_01', 'CAV_-1', 'CAR_1', 'CAV_1x', 'CAV_²', 'CAV_1 ', f'CAV_{last + 1}', 'HV1_0'):
        with pytest.raises(InputError, match='vehicle_id'):
            limits.check_vehicle(make_vehicle(bad, 'CAV'))


def test_graph_rejects_lanes_outside_its_one_hot_and_keeps_its_slots(project_config):
    road = project_config.scenario.road
    builder = GraphBuilder(project_config.graph, 500.0, road.highway_speed_limit, road.lane_count)
    before = builder.build([make_vehicle('HV1_0', lane=2), make_vehicle('CAV_0', 'CAV', position=20.0)])
    for lane in (3, -1, 127, -128):
        with pytest.raises(GraphInputError):
            builder.build([make_vehicle('HV1_1', lane=lane)])
    after = builder.build([make_vehicle('HV1_0', lane=2), make_vehicle('CAV_0', 'CAV', position=20.0)])
    assert after.vehicle_ids == before.vehicle_ids and np.array_equal(after.features, before.features)


def test_commands_non_finite_rejected_out_of_range_clamped(project_config):
    limits = CommandLimits.of(project_config.env.actions)
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(InputError, match='not finite'):
            limits.sanitize({'CAV_0': CavCommand(0, 1.0), 'CAV_1': CavCommand(0, bad)})
    with pytest.raises(InputError, match='lane_change'):
        limits.sanitize({'CAV_0': CavCommand(7, 1.0)})
    commands, clamped = limits.sanitize({'CAV_0': CavCommand(0, 3e38), 'CAV_1': CavCommand(1, -3e38),
                                         'CAV_2': CavCommand(-1, 1.5)})
    assert clamped == 2
    assert commands == {'CAV_0': CavCommand(0, project_config.env.actions.acceleration_max),
                        'CAV_1': CavCommand(1, project_config.env.actions.acceleration_min),
                        'CAV_2': CavCommand(-1, 1.5)}


def feed(gate: StepGate, messages) -> list:
    """The (episode, step) messages a gate takes, in order."""
    taken = []
    for episode, step in messages:
        if gate.refuse(episode, step) is None:
            gate.accept(episode, step)
            taken.append((episode, step))
    return taken


def test_one_bad_sequence_number_changes_nothing_later():
    good = [(4, step) for step in range(30)]
    clean = feed(_started(StepGate(1500), 4), good)
    assert clean == good
    for bad in [(4 + 1000, 3), (4, 2**32 - 1), (4, 1500), (4, 400), (4, 45), (3, 5), (4, 0)]:
        messages = good[:4] + [bad] + good[4:]
        taken = feed(_started(StepGate(1500), 4), messages)
        assert taken == good, bad
    # the known limit: a step that could really come next (within max_gap) cannot be told from a
    # good one; it costs the good messages up to it, never more
    taken = feed(_started(StepGate(1500, max_gap=10), 4), good[:4] + [(4, 12)] + good[4:])
    assert taken == good[:4] + [(4, 12)] + good[13:]


def _started(gate: StepGate, episode: int) -> StepGate:
    gate.start(episode)
    return gate


def test_gate_follows_only_a_started_episode_and_a_stream_that_really_moved_on():
    gate = StepGate(1500, max_gap=10)
    assert gate.check(0, 0) is not None, 'nothing is taken before an episode starts'
    gate.start(7)
    assert feed(gate, [(7, 600), (7, 601), (7, 602)]) == [(7, 602)], 'a node that joins mid-episode follows'
    gate.announce(8)
    assert feed(gate, [(8, 35), (8, 0), (8, 5)]) == [(8, 0), (8, 5)], "an episode begins at its start"
    gate.announce(7)
    assert feed(gate, [(7, 600), (7, 601), (7, 602)]) == [(7, 602)], 'or where a node that joins late finds it'
    # a node that stalled and lost 100 steps follows again after three steps that follow each other
    assert feed(gate, [(7, 701), (7, 702), (7, 703), (7, 704)]) == [(7, 703), (7, 704)]
    gate.announce(0)                               # a restarted bridge, a replayed bag
    assert feed(gate, [(0, 0), (0, 1)]) == [(0, 0), (0, 1)]


def test_an_episode_start_no_message_of_its_episode_follows_changes_nothing():
    """A stray or forged EVENT_STARTED (another episode, or the one running), before or after the
    bridge's next one, leaves the running episode's messages as they were and the bridge's next
    episode beginning with its first message."""
    good = [(4, step) for step in range(30)]
    for forged in (4 + 1000, 3, 0, 4, 5, 2**32 - 1):
        for forged_first in (True, False):
            gate = _started(StepGate(1500), 4)
            assert feed(gate, good[:10]) == good[:10]
            if forged_first:
                gate.announce(forged)
            assert feed(gate, good[10:]) == good[10:], forged
            gate.announce(5)
            if not forged_first:
                gate.announce(forged)
            assert feed(gate, [(4, 30), (5, 0), (4, 31), (5, 1)]) == [(4, 30), (5, 0), (5, 1)], \
                (forged, 'the pass before follows until the next episode begins, then not')
    # the same episode again (a looped bag's next pass) begins with a step back ...
    gate = _started(StepGate(1500), 4)
    feed(gate, good)
    gate.announce(4)
    assert feed(gate, [(4, 29), (4, 30), (4, 0), (4, 31), (4, 1)]) == [(4, 30), (4, 0), (4, 1)]
    # ... but not once the running pass has gone on for more than the gap since that start came
    gate = _started(StepGate(1500), 4)
    feed(gate, good[:10])
    gate.announce(4)
    assert feed(gate, good[10:] + [(4, 3), (4, 30)]) == good[10:] + [(4, 30)]
    # a flood of forged starts during the episode does not push out the bridge's next one
    gate = _started(StepGate(1500), 4)
    for forged in range(1000, 1000 + 3 * MAX_ANNOUNCED):
        gate.announce(forged)
    gate.announce(5)
    assert len(gate.announced) == MAX_ANNOUNCED and feed(gate, [(5, 0), (5, 1)]) == [(5, 0), (5, 1)]
    # the known limit: a forged start together with a message that begins its episode is what a
    # new bridge sends; the gate follows it
    gate = _started(StepGate(1500), 4)
    feed(gate, good[:10])
    gate.announce(1004)
    assert feed(gate, [(1004, 0), (4, 10)]) == [(1004, 0)]
