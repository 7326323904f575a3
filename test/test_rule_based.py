"""The rule-based driver's lane plan and speed choice on hand-made traffic."""
import pytest

from exit_decision.actions import ActionGrid
from exit_decision.agents.rule_based import RuleBasedDriver
from exit_decision.agents.shield import Shield
from exit_decision.config import GraphConfig
from exit_decision.graph import GraphBuilder
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import TrafficSnapshot

from conftest import make_vehicle


@pytest.fixture(scope='module')
def driver(project_config):
    geometry = RoadGeometry.of(project_config.scenario.road)
    grid = ActionGrid(project_config.env.actions)
    shield = Shield(project_config.env.shield, grid, geometry, 0.5)
    return RuleBasedDriver(grid, shield, geometry, project_config.scenario.road.ramp_speed_limit,
                           project_config.env.rule_based)


def decide(driver, vehicles):
    graph = GraphBuilder(GraphConfig(max_vehicles=10, sensing_range=30.0, feature_set='paper'),
                         500.0, 25.0).build(vehicles)
    decision = driver.decide(graph, TrafficSnapshot(vehicles))
    return {vid: driver.grid.command(index) for vid, index in decision.actions.items()}


def test_leaves_lane_0_before_exit_0_and_moves_right_after_it(driver):
    before_exit_0 = make_vehicle('a', 'CAV', lane=0, position=60.0)
    after_exit_0 = make_vehicle('b', 'CAV', lane=1, position=200.0, edge='Highway_1')
    commands = decide(driver, [before_exit_0, after_exit_0])
    assert commands['a'].lane_change == 1
    assert commands['b'].lane_change == -1


def test_waits_for_a_gap_instead_of_cutting_in(driver):
    cav = make_vehicle('cav', 'CAV', lane=1, position=200.0, speed=20.0, edge='Highway_1')
    beside = make_vehicle('hv', 'HV1', lane=0, position=201.0, speed=20.0, edge='Highway_1')
    commands = decide(driver, [cav, beside])
    assert commands['cav'].lane_change == 0
    assert commands['cav'].acceleration < 0, 'drops back behind the vehicle beside'


def test_slows_to_the_ramp_limit_before_exit_1(driver, project_config):
    geometry = driver.geometry
    cav = make_vehicle('cav', 'CAV', lane=0, position=geometry.diverge_at['Highway_1'] - 20.0, speed=25.0,
                       edge='Highway_1')
    assert decide(driver, [cav])['cav'].acceleration < 0
    assert driver.desired_speed(cav) < 25.0


def test_drops_behind_a_follower_that_slows_with_it_near_the_exit(driver):
    """Near Exit_1 the CAV slows for the ramp; a human just behind in lane 0 slows with it.
    Pulling ahead is not possible, so it must drop back firmly, not ride alongside."""
    cav = make_vehicle('cav', 'CAV', lane=1, position=300.0, speed=19.0, edge='Highway_1')
    follower = make_vehicle('hv2', 'HV2', lane=0, position=292.0, speed=19.0, edge='Highway_1')
    ahead = make_vehicle('lead', 'HV2', lane=0, position=340.0, speed=16.0, edge='Highway_1')
    commands = decide(driver, [cav, follower, ahead])
    assert commands['cav'].lane_change == 0
    assert commands['cav'].acceleration <= -2.0


def test_pulls_ahead_of_a_slower_follower_when_its_lane_is_free(driver):
    cav = make_vehicle('cav', 'CAV', lane=2, position=40.0, speed=20.0)
    follower = make_vehicle('hv', 'HV1', lane=1, position=33.0, speed=15.0)
    commands = decide(driver, [cav, follower])
    assert commands['cav'].lane_change == 0
    assert commands['cav'].acceleration >= -1.0, 'keeps ahead of the follower (dropping back brakes harder)'


def test_off_grid_command_is_the_rules_acceleration_within_the_shields_range(driver):
    """The options' low level: a CAV nearing the lane's limit on a free road keeps a small
    acceleration that the grid would round down to 0 (and so never reach 25 m/s); behind a
    close, slower leader the command stays within what the shield allows."""
    free = make_vehicle('free', 'CAV', lane=1, position=60.0, speed=24.0)
    snapshot = TrafficSnapshot([free])
    command = driver.command(free, driver.shield.mask(free, snapshot), snapshot)
    assert command.lane_change == 0
    assert 0.0 < command.acceleration < 0.5, 'below the grid\'s first step up'
    assert command.acceleration == pytest.approx(driver.acceleration(free, snapshot))
    cav = make_vehicle('cav', 'CAV', lane=1, position=60.0, speed=20.0)
    leader = make_vehicle('lead', 'HV1', lane=1, position=95.0, speed=10.0)
    snapshot = TrafficSnapshot([cav, leader])
    mask = driver.shield.mask(cav, snapshot)
    command = driver.command(cav, mask, snapshot)
    allowed = driver.grid.acceleration_of[mask & driver.grid.rows(command.lane_change)]
    assert allowed.max() < 0, 'the shield asks for braking here'
    assert allowed.min() <= command.acceleration <= allowed.max()


def test_commands_of_every_cav_match_the_grid_drivers_lane_changes(driver):
    vehicles = [make_vehicle('a', 'CAV', lane=0, position=60.0),
                make_vehicle('b', 'CAV', lane=1, position=200.0, edge='Highway_1')]
    graph = GraphBuilder(GraphConfig(max_vehicles=10, sensing_range=30.0, feature_set='paper'),
                         500.0, 25.0).build(vehicles)
    commands = driver.commands(graph, TrafficSnapshot(vehicles))
    grid_commands = decide(driver, vehicles)
    assert set(commands) == {'a', 'b'}
    assert {vid: c.lane_change for vid, c in commands.items()} == \
        {vid: c.lane_change for vid, c in grid_commands.items()}


def test_connected_cavs_make_room_for_a_cav_merging_ahead(driver):
    """The options' low level (connected_cavs): a CAV keeping lane 1 follows, as a virtual
    leader, a CAV just ahead in lane 0 that must leave lane 0 before Exit_0; the merger holds
    its speed and waits for the gap. The grid's rules cut in instead."""
    connected = RuleBasedDriver(driver.grid, driver.shield, driver.geometry, driver.ramp_speed_limit,
                                driver.parameters.model_copy(update={'connected_cavs': True}))
    keeper = make_vehicle('keeper', 'CAV', lane=1, position=60.0, speed=20.0)
    merger = make_vehicle('merger', 'CAV', lane=0, position=66.0, speed=20.0)
    snapshot = TrafficSnapshot([keeper, merger])
    free = driver.preferred(keeper, snapshot)
    lane_change, made_room = connected.preferred(keeper, snapshot)
    assert lane_change == 0 and made_room < free[1] and made_room < 0
    assert connected.preferred(merger, snapshot) == (0, pytest.approx(connected.acceleration(merger, snapshot))), \
        'holds its own lane\'s speed'
    assert driver.preferred(merger, snapshot)[0] == 1, \
        'the grid\'s rules cut in 1 m ahead of the CAV (their IDM check stops at the firm braking)'
    behind = make_vehicle('merger', 'CAV', lane=0, position=50.0, speed=20.0)   # not ahead: no room made
    assert connected.preferred(keeper, TrafficSnapshot([keeper, behind]))[1] == pytest.approx(
        driver.preferred(keeper, TrafficSnapshot([keeper, behind]))[1])
