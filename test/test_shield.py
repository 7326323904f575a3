"""Each action mask on hand-made traffic, and masked actions never chosen."""
import numpy as np
import pytest

from exit_decision.actions import ActionGrid
from exit_decision.agents.shield import Shield
from exit_decision.scenario.geometry import RoadGeometry
from exit_decision.traffic import HIGHWAY, TrafficSnapshot

from conftest import make_vehicle


@pytest.fixture(scope='module')
def geometry(project_config):
    return RoadGeometry.of(project_config.scenario.road)


def shield_with(project_config, geometry, **overrides):
    config = project_config.env.shield.model_copy(update=overrides)
    return Shield(config, ActionGrid(project_config.env.actions), geometry, decision_time=0.5)


def lanes_allowed(shield, mask):
    return {int(c) for c in shield.grid.lane_changes if mask[shield.grid.lane_change_of == c].any()}


def test_lanes_that_do_not_exist_and_diverge_zones(project_config, geometry):
    shield = shield_with(project_config, geometry)
    lane0 = make_vehicle('cav', 'CAV', lane=0, position=50.0)
    lane2 = make_vehicle('cav', 'CAV', lane=2, position=50.0)
    assert lanes_allowed(shield, shield.mask(lane0, TrafficSnapshot([lane0]))) == {0, 1}
    assert lanes_allowed(shield, shield.mask(lane2, TrafficSnapshot([lane2]))) == {-1, 0}
    near_diverge = make_vehicle('cav', 'CAV', lane=1, position=geometry.diverge_at['Highway_0'] - 3.0)
    assert lanes_allowed(shield, shield.mask(near_diverge, TrafficSnapshot([near_diverge]))) == {0}
    on_ramp = make_vehicle('cav', 'CAV', lane=0, position=200.0, edge='Exit_0', limit=15.0)
    assert lanes_allowed(shield, shield.mask(on_ramp, TrafficSnapshot([on_ramp]))) == {0}


def test_lane_change_into_a_small_gap_is_masked(project_config, geometry):
    shield = shield_with(project_config, geometry)
    cav = make_vehicle('cav', 'CAV', lane=1, position=100.0, speed=20.0)
    beside = make_vehicle('hv', 'HV1', lane=0, position=102.0, speed=20.0)
    assert lanes_allowed(shield, shield.mask(cav, TrafficSnapshot([cav, beside]))) == {0, 1}
    off = shield_with(project_config, geometry, lane_gap=False, stop_capable=False)
    assert -1 in lanes_allowed(off, off.mask(cav, TrafficSnapshot([cav, beside])))


def test_fast_follower_in_the_target_lane_needs_more_room(project_config, geometry):
    shield = shield_with(project_config, geometry)
    cav = make_vehicle('cav', 'CAV', lane=1, position=100.0, speed=15.0)
    slow_behind = make_vehicle('hv', 'HV1', lane=0, position=88.0, speed=15.0)    # 7 m gap, not closing
    fast_behind = make_vehicle('hv', 'HV1', lane=0, position=88.0, speed=25.0)    # 7 m gap, closing at 10 m/s
    assert -1 in lanes_allowed(shield, shield.mask(cav, TrafficSnapshot([cav, slow_behind])))
    assert -1 not in lanes_allowed(shield, shield.mask(cav, TrafficSnapshot([cav, fast_behind])))


def test_only_stop_capable_accelerations_behind_a_slow_leader(project_config, geometry):
    shield = shield_with(project_config, geometry, lane_gap=False)
    cav = make_vehicle('cav', 'CAV', lane=1, position=100.0, speed=20.0)
    leader = make_vehicle('hv', 'HV1', lane=1, position=130.0, speed=10.0)        # 25 m gap
    mask = shield.mask(cav, TrafficSnapshot([cav, leader]))
    keep = shield.grid.lane_change_of == 0
    allowed = shield.grid.acceleration_of[keep & mask]
    assert allowed.max() < 0, 'must brake'
    assert -8.0 in allowed
    # and with the leader far ahead every acceleration is fine
    far = make_vehicle('hv', 'HV1', lane=1, position=300.0, speed=10.0)
    assert shield.mask(cav, TrafficSnapshot([cav, far]))[keep].all()


def test_no_hard_braking_with_a_human_close_behind(project_config, geometry):
    shield = shield_with(project_config, geometry, lane_gap=False, stop_capable=False)
    cav = make_vehicle('cav', 'CAV', lane=1, position=100.0, speed=20.0)
    human = make_vehicle('hv', 'HV1', lane=1, position=85.0, speed=20.0)          # 10 m behind
    cav_behind = make_vehicle('cav2', 'CAV', lane=1, position=85.0, speed=20.0)
    keep = shield.grid.lane_change_of == 0
    mask = shield.mask(cav, TrafficSnapshot([cav, human]))
    assert shield.grid.acceleration_of[keep & mask].min() > -4.5
    assert shield.mask(cav, TrafficSnapshot([cav, cav_behind]))[keep].all()


def test_two_cavs_cannot_claim_the_same_gap(project_config, geometry):
    shield = shield_with(project_config, geometry)
    front = make_vehicle('front', 'CAV', lane=0, position=100.0, speed=20.0)
    back = make_vehicle('back', 'CAV', lane=2, position=98.0, speed=20.0)
    vehicles = [front, back]
    wants_left_or_right = lambda vehicle, mask: int(np.flatnonzero(
        mask & (shield.grid.lane_change_of == (1 if vehicle.lane_index == 0 else -1))
        & (shield.grid.acceleration_of == 0.0))[0]) if (mask & (shield.grid.lane_change_of != 0)).any() \
        else int(np.flatnonzero(mask)[0])
    decision = shield.decide(TrafficSnapshot(vehicles), ['front', 'back'], wants_left_or_right)
    assert shield.grid.lane_change_of[decision.actions['front']] == 1
    assert -1 not in lanes_allowed(shield, decision.masks['back']), 'the gap in lane 1 is reserved'
    off = shield_with(project_config, geometry, gap_reservation=False)
    decision = off.decide(TrafficSnapshot(vehicles), ['front', 'back'], wants_left_or_right)
    assert off.grid.lane_change_of[decision.actions['back']] == -1


def test_a_chooser_picking_a_masked_action_is_an_error(project_config, geometry):
    shield = shield_with(project_config, geometry)
    cav = make_vehicle('cav', 'CAV', lane=0, position=50.0)
    right = int(np.flatnonzero(shield.grid.lane_change_of == -1)[0])
    with pytest.raises(ValueError, match='masked action'):
        shield.decide(TrafficSnapshot([cav]), ['cav'], lambda vehicle, mask: right)


def test_a_snapshot_with_an_added_vehicle_answers_like_one_built_with_it():
    vehicles = [make_vehicle(f'v{i}', lane=i % 3, position=10.0 * i) for i in range(12)]
    added = make_vehicle('new', 'CAV', lane=1, position=45.0)
    grown, built = TrafficSnapshot(vehicles).with_vehicle(added), TrafficSnapshot([*vehicles, added])
    for lane in range(3):
        for position in (0.0, 44.0, 45.0, 52.0, 200.0):
            assert grown.neighbours((HIGHWAY, lane), position, 5.0) == built.neighbours((HIGHWAY, lane), position, 5.0)
    assert grown.by_id['new'] is added and len(grown.vehicles) == 13


def test_lane_planner_keeps_the_policy_on_its_route_and_drives_cavs_off_it(project_config, geometry):
    from exit_decision.agents.lane_planner import LanePlanner
    shield = shield_with(project_config, geometry)
    planner = LanePlanner.of(project_config, shield)
    before_exit0 = make_vehicle('cav', 'CAV', lane=1, position=50.0)
    snapshot = TrafficSnapshot([before_exit0])
    # on its route before Exit_0: the policy decides, but may not change into Exit_0's lane
    assert planner.choose(before_exit0, shield.mask(before_exit0, snapshot), snapshot) is None
    assert lanes_allowed(shield, planner.restrict(before_exit0, shield.mask(before_exit0, snapshot))) == {0, 1}
    # after Exit_0, lane 0 is the route: no change to the left
    in_lane0 = make_vehicle('cav', 'CAV', lane=0, position=geometry.merge_done_at['Highway_0'] + 20.0)
    snapshot = TrafficSnapshot([in_lane0])
    assert lanes_allowed(shield, planner.restrict(in_lane0, shield.mask(in_lane0, snapshot))) == {0}
    # off its route (lane 0 before Exit_0): the rule-based driver's lane plan moves it left
    off_route = make_vehicle('cav', 'CAV', lane=0, position=50.0)
    snapshot = TrafficSnapshot([off_route])
    mask = shield.mask(off_route, snapshot)
    assert planner.restrict(off_route, mask) is mask
    chosen = planner.choose(off_route, mask, snapshot)
    assert chosen is not None and shield.grid.lane_change_of[chosen] == 1
    # past Exit_1's diverge the task is decided: any lane, the policy decides
    past = make_vehicle('cav', 'CAV', lane=1, position=geometry.diverge_at['Highway_1'] + 10.0)
    assert planner.on_route(past) and planner.on_route(past, 2)


def test_lane_planner_is_a_config_switch(project_config, geometry):
    from exit_decision.agents.lane_planner import LanePlanner
    off = project_config.model_copy(update={'env': project_config.env.model_copy(update={'lane_planner': False})})
    assert LanePlanner.of(off, shield_with(project_config, geometry)) is None


def test_the_leader_in_lane_0_before_an_exit_is_the_nearer_of_the_lane_and_the_ramp(project_config, geometry):
    """A vehicle already on the ramp ahead (before the diverge) counts as a leader in lane 0; on
    an equal gap the lane's own leader is the one taken, and lane 1 never looks at the ramp."""
    shield = shield_with(project_config, geometry)
    cav = make_vehicle('cav', 'CAV', lane=0, position=100.0)
    lane_leader = make_vehicle('lane', lane=0, position=140.0)
    for ramp_at, expected in ((130.0, 'ramp'), (140.0, 'lane'), (150.0, 'lane')):
        ramp = make_vehicle('ramp', lane=0, position=ramp_at, edge='Exit_0', limit=15.0)
        snapshot = TrafficSnapshot([cav, lane_leader, ramp])
        assert shield.leader(cav, 0, snapshot).leader.vehicle_id == expected, ramp_at
        assert shield.leader(cav, 0, snapshot, shield.around(cav, 0, snapshot)).leader.vehicle_id == expected
    assert shield.leader(cav, 1, TrafficSnapshot([cav, ramp])).leader is None
