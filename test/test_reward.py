"""The reward function matrix, each sub-reward pinned against hand-computed values, and its
vector form: owners, per-metre incentives, any mode's scalar from one vector."""
import dataclasses
import math
import shutil

import numpy as np
import pytest
import yaml

from exit_decision.config import ConfigError, default_config_dir, load_project
from exit_decision.reward import (BaselineReward, IntentionReward, MatrixReward, StepRewardInputs, TermsReward,
                                  mode_weights, scalar, weight_input)
from exit_decision.traffic import Arrival, Collision, StepResult, TrafficSnapshot

from conftest import make_vehicle

STEP = 0.1


@pytest.fixture()
def literal(project_config):
    return MatrixReward(project_config.reward('literal'), STEP)


@pytest.fixture()
def bounded(project_config):
    return MatrixReward(project_config.reward('bounded'), STEP)


@pytest.fixture()
def calibrated(project_config):
    return MatrixReward(project_config.reward('calibrated'), STEP)


def step_of(vehicles, arrivals=(), collisions=(), lane_changers=(), released=()):
    return StepResult(step=1, time=0.1, vehicles=list(vehicles), arrivals=list(arrivals),
                      collisions=list(collisions), lane_changers=list(lane_changers), released=frozenset(released))


def inputs(step, lane_changes=0):
    return StepRewardInputs(step, TrafficSnapshot(step.vehicles), lane_changes)


def test_result_rewards_exits_to_their_cav_or_shared_and_collisions_to_the_cavs_in_them(literal):
    step = step_of([], arrivals=[Arrival('c', 'CAV', 'Exit_1', True), Arrival('h', 'HV2', 'Exit_1', True),
                                 Arrival('x', 'CAV', 'Exit_0', False), Arrival('y', 'HV1', 'Exit_1', True)],
                   collisions=[Collision('a', 'b', 'HV1', 'HV2'), Collision('d', 'e', 'CAV', 'HV1')])
    own, shared = literal.raw(inputs(step))
    assert own['c'][0].tolist() == [300.0, 0.0]
    assert own['d'][0].tolist() == [0.0, -60000.0], 'one -60000 per step, owned by the CAV in a collision'
    assert shared[0].tolist() == [300.0, 0.0], 'an HV2 exit belongs to no CAV'
    _, shared = literal.raw(inputs(step_of([], collisions=[Collision('a', 'b', 'HV1', 'HV2')])))
    assert shared[0].tolist() == [0.0, -60000.0], 'a collision without a CAV is shared'


def test_efficiency_bands(literal):
    assert literal.efficiency_one(make_vehicle('a', 'CAV', speed=20.0)) == pytest.approx((math.exp(6 * 10 / 25), 0.0))
    assert literal.efficiency_one(make_vehicle('b', 'CAV', speed=27.0)) == pytest.approx((0.0, -math.exp(2.0)))
    assert literal.efficiency_one(make_vehicle('c', 'CAV', speed=4.0)) == pytest.approx((0.0, -math.exp(1 + 6 / 3)))
    ramp = make_vehicle('d', 'CAV', speed=10.0, edge='Exit_1', limit=15.0)   # v_min 5, v_max 15
    assert literal.efficiency_one(ramp) == pytest.approx((math.exp(6 * 5 / 15), 0.0))


def test_calibrated_incentives_count_per_metre_driven(calibrated, literal):
    cav = make_vehicle('a', 'CAV', speed=20.0, acceleration=0.0)
    metres = 20.0 * STEP
    assert calibrated.efficiency_one(cav)[0] == pytest.approx(literal.efficiency_one(cav)[0] * metres)
    assert calibrated.comfort_one(cav)[0] == pytest.approx(math.exp(3) * metres)
    standing = make_vehicle('s', 'CAV', speed=0.0)
    assert calibrated.comfort_one(standing)[0] == 0.0, 'standing still earns no incentive'


def test_headway_safety_row_pays_per_metre_graded_by_the_headway_kept(project_config, literal):
    """Issue 28's safety row: a standing CAV earns no safety incentive, even alone on the road;
    a closer (still safe) gap earns less than a longer one; Table 4's punishments stay."""
    headway = MatrixReward(project_config.reward('headway'), STEP)
    full = headway.config.headway_full
    standing = make_vehicle('s', 'CAV', position=100.0, speed=0.0)
    assert headway.safety(standing, TrafficSnapshot([standing]))[0] == 0.0
    alone = make_vehicle('a', 'CAV', position=100.0, speed=20.0)
    assert headway.safety(alone, TrafficSnapshot([alone]))[0] == pytest.approx(math.exp(2) * 20.0 * STEP)

    def incentive_behind(gap):
        cav = make_vehicle('cav', 'CAV', position=100.0, speed=20.0)
        leader = make_vehicle('l', position=100.0 + 5.0 + gap, speed=20.0)   # not closing: no punishment
        return headway.safety(cav, TrafficSnapshot([cav, leader]))

    close, far = incentive_behind(0.5 * full * 20.0), incentive_behind(2 * full * 20.0)
    assert close == pytest.approx((0.5 * math.exp(2) * 20.0 * STEP, 0.0))
    assert far == pytest.approx((math.exp(2) * 20.0 * STEP, 0.0))
    # a closing follower: the same punishment as the hazard diagram's
    cav = make_vehicle('cav', 'CAV', position=100.0, speed=20.0)
    follower = make_vehicle('f', position=85.0, speed=25.0)                    # 10 m at 5 m/s: 2 s
    snapshot = TrafficSnapshot([cav, follower])
    assert headway.safety(cav, snapshot)[1] == pytest.approx(literal.safety(cav, snapshot)[1])
    assert headway.safety(cav, snapshot)[1] < 0


def test_comfort_per_vehicle_and_the_shared_lane_change_term(literal):
    assert literal.comfort_one(make_vehicle('a', acceleration=1.9)) == pytest.approx((math.exp(3), 0.0))
    assert literal.comfort_one(make_vehicle('c', acceleration=-3.0)) == (0.0, 0.0)
    assert literal.comfort_one(make_vehicle('d', acceleration=-4.5)) == (0.0, -2000.0)
    assert literal.lane_change_punishment(4) == pytest.approx(-math.exp(2.0))


@pytest.mark.parametrize('t_follower, t_leader, expected', [
    (math.inf, math.inf, (math.exp(2), 0.0)),                                   # Omega_I3
    (6.0, math.inf, (math.exp((6 - 5) / 2.5), 0.0)),                            # Omega_I1
    (20.0, 30.0, (math.exp(2), 0.0)),                                           # capped at 10 s
    (2.0, 9.0, (math.exp((9 - 5) / 2.5), -math.exp(2.0))),                      # I2 + P1
    (1.0, 3.0, (0.0, -math.exp(3.0) - math.exp(1.0))),                          # P1 + P2
])
def test_safety_regions_of_the_hazard_diagram(literal, t_follower, t_leader, expected):
    assert literal.safety_one(t_follower, t_leader) == pytest.approx(expected)


def test_time_gaps_use_the_closing_vehicles_in_the_same_lane(literal):
    cav = make_vehicle('cav', 'CAV', position=100.0, speed=20.0)
    follower = make_vehicle('f', position=70.0, speed=25.0)    # closes 30 m at 5 m/s: 6 s
    leader = make_vehicle('l', position=130.0, speed=22.0)     # faster: not closing
    other_lane = make_vehicle('o', lane=1, position=105.0, speed=0.0)
    snapshot = TrafficSnapshot([cav, follower, leader, other_lane])
    assert literal.time_gaps(cav, snapshot) == (pytest.approx(6.0), math.inf)


def test_any_modes_scalar_from_one_vector_is_the_papers_trace_formula(literal, project_config):
    braking = make_vehicle('b', 'CAV', speed=15.0, acceleration=-6.0)
    cruising = make_vehicle('c', 'CAV', position=200.0, speed=20.0, acceleration=0.0)
    step = step_of([braking, cruising], arrivals=[Arrival('x', 'CAV', 'Exit_1', True)],
                   collisions=[Collision('h1', 'h2', 'HV1', 'HV1')])
    vector = literal.vector(inputs(step, lane_changes=2))
    own, shared = literal.raw(inputs(step, lane_changes=2))
    sub = shared + sum(own.values())
    s = sub[0, 1] + sub[2, 1]                       # r_result_P + r_comfort_P
    for name in ('CONP', 'AGGI', 'A1b'):
        mode = project_config.mode(name)
        k_i, k_p = mode.incentive, mode.punishment
        k_incentive = [k_i * math.exp(s / 100000), k_i * math.exp(s / 80000), k_i, k_i * math.exp(s / 150000)]
        k_decision = weight_input(mode)[:4]
        expected = sum(k_decision[i] * (k_incentive[i] * sub[i, 0] + k_p * sub[i, 1]) for i in range(4))
        assert scalar(vector.total(), mode_weights(mode)) == pytest.approx(expected)
    np.testing.assert_allclose(vector.total(), vector.shared + vector.per_vehicle['b'] + vector.per_vehicle['c']
                               + vector.per_vehicle['x'])


def test_a_released_cav_earns_nothing_more(calibrated):
    cav = make_vehicle('gone', 'CAV', speed=20.0)
    own, _ = calibrated.raw(inputs(step_of([cav], released=['gone'])))
    assert 'gone' not in own


def test_bounded_reward_stays_bounded_on_extreme_inputs(bounded, literal):
    runaway = make_vehicle('cav', 'CAV', speed=48.0)            # the probe's runaway CAV
    assert literal.efficiency_one(runaway)[1] == pytest.approx(-math.exp(23.0))
    assert bounded.efficiency_one(runaway)[1] == pytest.approx(-math.exp(5.0))
    assert bounded.lane_change_punishment(1000) == pytest.approx(-math.exp(5.0))
    assert literal.lane_change_punishment(60) == pytest.approx(-math.exp(30.0))
    step = step_of([runaway], collisions=[Collision('a', 'b', 'CAV', 'HV1')])
    total = scalar(bounded.vector(StepRewardInputs(step, TrafficSnapshot([runaway]), 1000)).total(),
                   np.full((4, 2), 0.5))
    assert math.isfinite(total) and -1000 < total < 0


def test_baseline_reward(project_config):
    reward = BaselineReward(project_config.reward('baseline'))
    cav = make_vehicle('cav', 'CAV', speed=25.0)
    step = step_of([cav, make_vehicle('h', speed=10.0)], arrivals=[Arrival('x', 'CAV', 'Exit_1', True)],
                   collisions=[Collision('a', 'b', 'HV1', 'HV1')], lane_changers=['cav', 'h'])
    c = project_config.reward('baseline')
    expected = c.intention + c.speed * 1.0 - c.lane_change * 1 - c.collision * 1
    total = reward.vector(inputs(step, 2)).total()
    for mode in ('AGGI', 'CONP'):
        assert scalar(total, reward.weights(project_config.mode(mode))) == pytest.approx(expected)


def per_cav_scores(reward, step, config):
    """Each CAV's score and the shared one, the same under every mode (a paper's reward has none)."""
    vector = reward.vector(inputs(step))
    scores = []
    for mode in ('AGGI', 'CONP'):
        weights = reward.weights(config.mode(mode))
        scores.append(({vid: scalar(v, weights) for vid, v in vector.per_vehicle.items()},
                       scalar(vector.shared, weights)))
    assert scores[0] == scores[1]
    return scores[0]


def test_paper_002_reward_weighs_safety_efficiency_and_lane_changes(project_config):
    c = project_config.reward('paper_002')
    assert (c.collision, c.speed, c.lane_change) == (-0.5, 0.4, -0.1), 'the paper\'s 0.5 / 0.4 / 0.1'
    fast = make_vehicle('fast', 'CAV', speed=25.0)                      # at the lane limit: 1
    slow = make_vehicle('slow', 'CAV', speed=17.5, lane=1)              # half way in [10, 25]: 0.5
    step = step_of([fast, slow, make_vehicle('gone', 'CAV', speed=25.0)], lane_changers=['slow', 'h'],
                   collisions=[Collision('fast', 'h', 'CAV', 'HV1'), Collision('a', 'b', 'HV1', 'HV2')],
                   released=['gone'])
    own, shared = per_cav_scores(TermsReward(c), step, project_config)
    assert own == pytest.approx({'fast': 0.2 * 0.4 * 1.0 - 0.5, 'slow': 0.2 * 0.4 * 0.5 - 0.1})
    assert shared == pytest.approx(-0.5), 'a collision without a CAV is shared'


def test_paper_003_reward_pays_steps_and_a_clean_exit(project_config):
    c = project_config.reward('paper_003')
    ramp = make_vehicle('cav', 'CAV', speed=5.0, edge='Exit_1', limit=15.0)   # at the ramp's v_min: 0
    step = step_of([ramp], arrivals=[Arrival('x', 'CAV', 'Exit_0', False)])
    own, _ = per_cav_scores(TermsReward(c), step, project_config)
    assert own == pytest.approx({'cav': 0.2 * c.step, 'x': c.clean_exit}), 'the task is no term of it'


def test_paper_001_reward_is_eq_5_on_the_intention_gradient(project_config):
    c = project_config.reward('paper_001')
    reward = IntentionReward(c, lambda position: range(1, 3) if position < 150 else range(0, 1))
    on = make_vehicle('on', 'CAV', lane=1, position=50.0, speed=24.0)     # R_S = 24/30 - 0.3 = 0.5
    off = make_vehicle('off', 'CAV', lane=0, position=50.0, speed=24.0)
    late = make_vehicle('late', 'CAV', lane=2, position=200.0, speed=24.0)
    ramp = make_vehicle('ramp', 'CAV', edge='Exit_1', speed=9.0, limit=15.0)   # R_S = 0: R_I > 0 pays nothing
    step = step_of([on, off, late, ramp], arrivals=[Arrival('done', 'CAV', 'Exit_1', True),
                                                    Arrival('lost', 'CAV', 'Highway_2', False)],
                   collisions=[Collision('on', 'h', 'CAV', 'HV1')])
    own, shared = per_cav_scores(reward, step, project_config)
    assert own == pytest.approx({
        'on': 1.0 * (0.2 * 1.0) * 0.5 + 2.0 * -1.0,     # w_I R_I R_S + w_C R_C, R_C = -(2 vehicles) / 2
        'off': 1.0 * (0.2 * -1.0),                      # R_I <= 0: w_I R_I
        'late': 1.0 * (0.2 * -1.0),
        'ramp': 0.0,
        'done': 1.0 * 2.0 * 1.0, 'lost': -2.0})
    assert shared == 0.0


# --- the `traffic` variant: the hard braking a CAV causes behind it (issue 39) -------------------

@pytest.fixture()
def traffic(project_config):
    return MatrixReward(project_config.reward('traffic'), STEP)


def test_traffic_variant_is_headway_plus_the_caused_braking_term(project_config):
    traffic, headway = project_config.reward('traffic'), project_config.reward('headway')
    assert traffic.model_dump(exclude={'caused_braking'}) == headway.model_dump(exclude={'caused_braking'})
    assert headway.caused_braking is None
    term = traffic.caused_braking
    assert (term.b_safe, term.leader_range) == (4.0, 50.0) and term.weight > 0
    assert project_config.env.reward_variant == 'headway', 'the default variant is unchanged'


def test_a_bad_key_in_the_traffic_variant_is_refused_by_name(tmp_path):
    target = tmp_path / 'config'
    shutil.copytree(default_config_dir(), target)
    data = yaml.safe_load((target / 'reward.yaml').read_text())
    data['variants']['traffic']['caused_braking']['b_saef'] = 4.0
    (target / 'reward.yaml').write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r'reward\.yaml(.|\n)*traffic\.matrix\.caused_braking\.b_saef'):
        load_project(target)


def behind(leader_class, follower_acceleration, gap=10.0, leader_id='lead'):
    """A leader at 100 m and a follower ``gap`` metres (bumper to bumper) behind it."""
    leader = make_vehicle(leader_id, leader_class, position=100.0, speed=15.0)
    follower = make_vehicle(f'{leader_id}_f', position=100.0 - 5.0 - gap, speed=15.0,
                            acceleration=follower_acceleration)
    return [leader, follower]


def test_no_hard_braking_behind_a_cav_costs_it_nothing(traffic, project_config):
    headway = MatrixReward(project_config.reward('headway'), STEP)
    step = step_of(behind('CAV', -4.0) + behind('CAV', 1.0, leader_id='c2'))     # at b_safe: not beyond it
    assert traffic.caused_braking(step, TrafficSnapshot(step.vehicles)) == {}
    own, shared = traffic.raw(inputs(step))
    expected_own, expected_shared = headway.raw(inputs(step))
    assert own.keys() == expected_own.keys()
    for vehicle_id in own:
        np.testing.assert_allclose(own[vehicle_id], expected_own[vehicle_id])
    np.testing.assert_allclose(shared, expected_shared)


def test_caused_braking_is_charged_to_the_cav_leader_only(traffic, project_config):
    """A follower braking beyond b_safe charges its CAV leader's comfort punishment, nothing
    else; behind a human, too far behind, or behind a released CAV it charges nobody."""
    headway = MatrixReward(project_config.reward('headway'), STEP)
    weight = traffic.config.caused_braking.weight
    groups = {'cav': behind('CAV', -6.0, leader_id='cav'),                # lane 0: charged
              'human': behind('HV1', -6.0, leader_id='human'),            # lane 1: a human leader
              'far': behind('CAV', -6.0, gap=60.0, leader_id='far'),      # lane 2: beyond leader_range
              'gone': behind('CAV', -6.0, leader_id='gone')}              # on a ramp, released
    vehicles = [dataclasses.replace(v, lane_index=lane) for lane, key in enumerate(('cav', 'human', 'far'))
                for v in groups[key]]
    vehicles += [dataclasses.replace(v, edge_id='Exit_1', on_highway=False, lane_speed_limit=15.0)
                 for v in groups['gone']]
    step = step_of(vehicles, released=['gone'])
    assert traffic.caused_braking(step, TrafficSnapshot(step.vehicles)) == pytest.approx({'cav': -2.0 * weight})
    own, shared = traffic.raw(inputs(step))
    expected_own, expected_shared = headway.raw(inputs(step))
    np.testing.assert_allclose(shared, expected_shared)
    for vehicle_id in expected_own:
        difference = own[vehicle_id] - expected_own[vehicle_id]
        charged = np.zeros((4, 2))
        if vehicle_id == 'cav':
            charged[2, 1] = -2.0 * weight          # the comfort row's punishment
        np.testing.assert_allclose(difference, charged, err_msg=vehicle_id)


def test_caused_braking_is_proportional_to_the_excess_deceleration(traffic):
    weight, b_safe = traffic.config.caused_braking.weight, traffic.config.caused_braking.b_safe

    def charge(acceleration):
        step = step_of(behind('CAV', acceleration))
        return traffic.caused_braking(step, TrafficSnapshot(step.vehicles)).get('lead', 0.0)

    assert charge(-(b_safe + 0.5)) == pytest.approx(-0.5 * weight)
    assert charge(-(b_safe + 3.0)) == pytest.approx(6 * charge(-(b_safe + 0.5)))
    assert charge(-b_safe) == 0.0


def test_caused_braking_reaches_the_cavs_own_credit_in_the_vector(traffic):
    step = step_of(behind('CAV', -7.0))
    vector = traffic.vector(inputs(step))
    own, _ = traffic.raw(inputs(step))
    assert own['lead'][2, 1] == pytest.approx(-3.0 * traffic.config.caused_braking.weight)
    assert vector.per_vehicle['lead'][2, 1] == pytest.approx(own['lead'][2, 1] / traffic.config.scales.comfort)
