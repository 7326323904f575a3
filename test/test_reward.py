"""The reward function matrix, each sub-reward pinned against hand-computed values."""
import math

import numpy as np
import pytest

from exit_decision.reward import BaselineReward, MatrixReward, StepRewardInputs
from exit_decision.traffic import Arrival, Collision, StepResult, TrafficSnapshot

from conftest import make_vehicle


@pytest.fixture()
def literal(project_config):
    return MatrixReward(project_config.reward('literal'), project_config.mode('CONP'))


@pytest.fixture()
def bounded(project_config):
    return MatrixReward(project_config.reward('bounded'), project_config.mode('AGGI'))


def step_of(vehicles, arrivals=(), collisions=(), lane_changers=()):
    return StepResult(step=1, time=0.1, vehicles=list(vehicles), arrivals=list(arrivals),
                      collisions=list(collisions), lane_changers=list(lane_changers))


def test_result_rewards_exit_1_of_cavs_and_hv2_and_punishes_any_collision(literal):
    step = step_of([], arrivals=[Arrival('c', 'CAV', 'Exit_1'), Arrival('h', 'HV2', 'Exit_1'),
                                 Arrival('x', 'CAV', 'Exit_0'), Arrival('y', 'HV1', 'Exit_1')],
                   collisions=[Collision('a', 'b', 'HV1', 'HV2'), Collision('c', 'd', 'CAV', 'HV1')])
    assert literal.result(step) == (600.0, -60000.0)
    assert literal.result(step_of([])) == (0.0, 0.0)


def test_efficiency_bands(literal):
    in_band = make_vehicle('a', 'CAV', speed=20.0)                 # v_min 10, v_max 25
    too_fast = make_vehicle('b', 'CAV', speed=27.0)
    too_slow = make_vehicle('c', 'CAV', speed=4.0)
    ramp = make_vehicle('d', 'CAV', speed=10.0, edge='Exit_1', limit=15.0)  # v_min 5, v_max 15
    assert literal.efficiency([in_band]) == pytest.approx((math.exp(6 * 10 / 25), 0.0))
    assert literal.efficiency([too_fast]) == pytest.approx((0.0, -math.exp(2.0)))
    assert literal.efficiency([too_slow]) == pytest.approx((0.0, -math.exp(1 + 6 / 3)))
    assert literal.efficiency([ramp]) == pytest.approx((math.exp(6 * 5 / 15), 0.0))


def test_comfort_counts_smooth_vehicles_braking_and_lane_changes(literal):
    vehicles = [make_vehicle('a', acceleration=1.9), make_vehicle('b', acceleration=-2.0),
                make_vehicle('c', acceleration=-3.0), make_vehicle('d', acceleration=-4.5),
                make_vehicle('e', 'CAV', acceleration=-6.0)]
    incentive, punishment = literal.comfort(vehicles, lane_changes=4)
    assert incentive == pytest.approx(2 * math.exp(3))
    assert punishment == pytest.approx(-2000 * 2 - math.exp(2.0))


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


def test_trace_formula_equals_the_weighted_sum(literal, project_config):
    sub = np.array([[300.0, -60000.0], [10.0, -3.0], [200.0, -2001.0], [7.0, -5.0]])
    breakdown = literal.combine(sub)
    mode = project_config.mode('CONP')
    s = -60000.0 - 2001.0
    k_incentive = [0.4 * math.exp(s / 100000), 0.4 * math.exp(s / 80000), 0.4, 0.4 * math.exp(s / 150000)]
    k_decision = [mode.decision_weights.result, mode.decision_weights.efficiency,
                  mode.decision_weights.comfort, mode.decision_weights.safety]
    expected = sum(k_decision[i] * (k_incentive[i] * sub[i, 0] + 0.6 * sub[i, 1]) for i in range(4))
    assert breakdown.total == pytest.approx(expected)
    np.testing.assert_allclose(breakdown.weights[:, 0], k_incentive)


def test_bounded_reward_stays_bounded_on_extreme_inputs(bounded, literal):
    runaway = make_vehicle('cav', 'CAV', speed=48.0)            # the probe's runaway CAV
    assert literal.efficiency([runaway])[1] == pytest.approx(-math.exp(23.0))
    assert bounded.efficiency([runaway])[1] == pytest.approx(-math.exp(5.0))
    assert bounded.comfort([], lane_changes=1000)[1] == pytest.approx(-math.exp(5.0))
    assert literal.comfort([], lane_changes=60)[1] == pytest.approx(-math.exp(30.0))
    step = step_of([runaway] * 15, collisions=[Collision('a', 'b', 'CAV', 'HV1')])
    total = bounded(StepRewardInputs(step, TrafficSnapshot([runaway]), 1000)).total
    assert math.isfinite(total) and -1000 < total < 0


def test_baseline_reward(project_config):
    reward = BaselineReward(project_config.reward('baseline'))
    cav = make_vehicle('cav', 'CAV', speed=25.0)
    step = step_of([cav, make_vehicle('h', speed=10.0)], arrivals=[Arrival('x', 'CAV', 'Exit_1')],
                   collisions=[Collision('a', 'b', 'HV1', 'HV1')], lane_changers=['cav', 'h'])
    c = project_config.reward('baseline')
    expected = c.intention + c.speed * 1.0 - c.lane_change * 1 - c.collision * 1
    assert reward(StepRewardInputs(step, TrafficSnapshot(step.vehicles), 2)).total == pytest.approx(expected)
