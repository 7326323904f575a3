"""The episode metrics (defined in exit_decision/episode_log.py) from a hand-made episode log."""
import math

import numpy as np
import pytest

from exit_decision.episode_log import METRICS, TTC_CAP, EpisodeLog
from exit_decision.evaluation.metrics import markdown_table, summarize
from exit_decision.traffic import Arrival, Collision, StepResult, TrafficSnapshot

from conftest import make_vehicle


def scored(value):
    """A reward vector that the log's weights (1 on the result incentive) score as ``value``."""
    vector = np.zeros((4, 2))
    vector[0, 0] = value
    return vector


def test_metrics_of_a_hand_made_episode():
    weights = np.zeros((4, 2))
    weights[0, 0] = 1.0
    log = EpisodeLog(braking_threshold=-4.5, reward_weights=weights)
    cav1, cav2 = make_vehicle('c1', 'CAV', speed=20.0), make_vehicle('c2', 'CAV', speed=10.0)
    hv2 = make_vehicle('h2', 'HV2', speed=30.0)
    log.record(StepResult(1, 0.1, [cav1, cav2, hv2]), scored(1.0))
    # c1 brakes hard for two steps (one event), h2 once later (a second event)
    braking = make_vehicle('c1', 'CAV', speed=20.0, acceleration=-5.0)
    log.record(StepResult(2, 0.2, [braking, cav2, hv2], braking_starts=['c1']), scored(2.0))
    log.record(StepResult(3, 0.3, [braking, cav2], arrivals=[Arrival('h2', 'HV2', 'Exit_1', True)],
                          collisions=[Collision('c2', 'x', 'CAV', 'HV1'), Collision('y', 'z', 'HV1', 'HV3')]),
               scored(-3.0))
    log.record(StepResult(4, 0.4, [], arrivals=[Arrival('c1', 'CAV', 'Exit_1', True)]))
    m = log.metrics()
    assert m['v_AVs'] == pytest.approx((20 + 10) * 3 / 6)
    assert m['v_s'] == pytest.approx(((20 + 10 + 30) * 2 + 20 + 10) / 8)
    assert m['p_collision'] == pytest.approx(2 / 2)
    assert m['p_collision_CAV'] == pytest.approx(1 / 2)
    assert m['N_braking'] == 1 and m['braking_steps'] == 2
    assert m['p_CAV'] == pytest.approx(0.5) and m['p_HV2'] == pytest.approx(1.0)
    assert m['reward'] == pytest.approx(0.0) and m['steps'] == 4
    assert m['N_braking_CAV'] == 1
    assert math.isnan(m['headway_CAV']), 'no snapshot given: no headway counted'
    assert math.isnan(m['N_braking_caused_CAV']) and math.isnan(m['min_TTC']), 'nor what the traffic pays'


def test_cav_time_headway_counts_close_leaders_of_moving_cavs_only():
    log = EpisodeLog()
    cav = make_vehicle('c', 'CAV', lane=1, position=100.0, speed=20.0)
    leader = make_vehicle('l', 'HV1', lane=1, position=135.0, speed=20.0)          # 30 m bumper gap
    slow = make_vehicle('s', 'CAV', lane=0, position=100.0, speed=4.0)             # too slow to count
    slow_leader = make_vehicle('sl', 'HV3', lane=0, position=110.0, speed=4.0)
    far = make_vehicle('f', 'CAV', lane=2, position=100.0, speed=20.0)
    far_leader = make_vehicle('fl', 'HV1', lane=2, position=300.0, speed=20.0)     # beyond 100 m
    vehicles = [cav, leader, slow, slow_leader, far, far_leader]
    log.record(StepResult(1, 0.1, vehicles), snapshot=TrafficSnapshot(vehicles))
    assert log.metrics()['headway_CAV'] == pytest.approx(30.0 / 20.0)


def record(log, step, vehicles, braking_starts=()):
    log.record(StepResult(step, step / 10, vehicles, braking_starts=list(braking_starts)),
               snapshot=TrafficSnapshot(vehicles))


def test_brakings_caused_by_cavs_and_the_minimum_time_to_collision():
    """Lane 0: an HV1 brakes hard behind a CAV (caused), twice in a row (one event), then again
    (a second event); lane 1: an HV1 brakes behind an HV3 (not caused); lane 2: a CAV brakes hard
    behind a CAV 60 m ahead (beyond the range: not caused). TTC: lane 0 closes 10 m at 5 m/s (2 s),
    lane 1 20 m at 4 m/s (5 s), lane 2 opens."""
    log = EpisodeLog()

    def vehicles(brake_0, brake_1, brake_2):
        return [make_vehicle('c', 'CAV', lane=0, position=100.0, speed=10.0),
                make_vehicle('h', 'HV1', lane=0, position=85.0, speed=15.0, acceleration=brake_0),
                make_vehicle('l', 'HV3', lane=1, position=100.0, speed=10.0),
                make_vehicle('g', 'HV1', lane=1, position=75.0, speed=14.0, acceleration=brake_1),
                make_vehicle('c2', 'CAV', lane=2, position=170.0, speed=20.0),
                make_vehicle('c3', 'CAV', lane=2, position=105.0, speed=10.0, acceleration=brake_2)]

    record(log, 1, vehicles(-5.0, -5.0, -5.0), braking_starts=['h', 'g', 'c3'])
    record(log, 2, vehicles(-5.0, 0.0, -5.0))
    record(log, 3, vehicles(0.0, 0.0, 0.0))
    record(log, 4, vehicles(-6.0, 0.0, 0.0), braking_starts=['h'])
    m = log.metrics()
    assert m['N_braking'] == 4 and m['N_braking_caused_CAV'] == 2
    assert m['min_TTC'] == pytest.approx(2.0) and m['min_TTC_CAV'] == pytest.approx(2.0)
    # without a CAV ahead of a closing follower, min_TTC_CAV stays at the cap
    log = EpisodeLog()
    record(log, 1, vehicles(0.0, 0.0, 0.0)[2:])
    m = log.metrics()
    assert m['min_TTC'] == pytest.approx(5.0) and m['min_TTC_CAV'] == TTC_CAP
    assert m['N_braking_caused_CAV'] == 0


def test_empty_log_gives_nan_not_zero_division():
    m = EpisodeLog().metrics()
    assert math.isnan(m['p_CAV']) and math.isnan(m['v_AVs'])


def test_summary_and_table():
    episodes = [dict.fromkeys(METRICS, v) for v in (1.0, 3.0)]
    summary = summarize(episodes)
    assert summary['p_CAV'] == (2.0, 1.0)
    assert '| run-a | 2 ± 1 |' in markdown_table([('run-a', summary)])


def test_the_table_leaves_out_a_metric_no_run_measured():
    measured = {m: 1.0 for m in METRICS if m != 'headway_CAV'}
    table = markdown_table([('stack', summarize([measured])), ('also', summarize([measured]))])
    assert 'headway_CAV' not in table and 'nan' not in table and '| p_CAV |' in table
    table = markdown_table([('stack', summarize([measured])), ('env', summarize([dict.fromkeys(METRICS, 2.0)]))])
    assert 'headway_CAV' in table and '| env |' in table
