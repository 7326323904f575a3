"""A road with other edge names and other lengths needs no code change (issue 11): it builds,
and an episode on it is the episode on the shipped names, name for name."""
import re

import pytest

from exit_decision.config import deep_merge, load_project
from exit_decision.env import ExitDecisionEnv
from exit_decision.driving.fixed import rule_based
from exit_decision.driving.episode import play_episode
from exit_decision.scenario.geometry import RoadGeometry

#: 9 vehicles, 3 of them CAVs, on a road with every section half its shipped length
HALF = {'max_steps': 300, 'road': {'highway_lengths': [75.0, 100.0, 75.0]},
        'vehicle_classes': {'HV1': {'count': 3}, 'HV2': {'count': 2}, 'HV3': {'count': 1}, 'CAV': {'count': 3}}}
RENAMED = deep_merge(HALF, {'road': {'names': {'sections': ['Road_A', 'Road_B', 'Road_C'],
                                               'first_exit': 'Ramp_X', 'target_exit': 'Ramp_Y'}}})
#: renamed edge -> the shipped name of the same edge
SHIPPED_NAME = {'Road_A': 'Highway_0', 'Road_B': 'Highway_1', 'Road_C': 'Highway_2', 'Ramp_X': 'Exit_0',
                'Ramp_Y': 'Exit_1'}


def test_the_renamed_half_length_road_builds_with_its_names_and_lengths():
    shipped = RoadGeometry.of(load_project().scenario.road)
    geometry = RoadGeometry.of(load_project(scenario_override=RENAMED).scenario.road)
    edges = set(re.findall(r'<edge id="([^:"][^"]*)"', geometry.net_file.read_text()))
    assert edges == set(SHIPPED_NAME)
    assert geometry.sections == ('Road_A', 'Road_B', 'Road_C')
    assert (geometry.first_exit.ramp, geometry.first_exit.section) == ('Ramp_X', 'Road_A')
    assert (geometry.target_exit.ramp, geometry.target_exit.section) == ('Ramp_Y', 'Road_B')
    junction = shipped.first_exit.merge_done_at - shipped.first_exit.diverge_at
    assert geometry.first_exit.diverge_at == pytest.approx(75.0)
    assert geometry.target_exit.diverge_at == pytest.approx(75.0 + junction + 100.0)
    assert geometry.road_length == pytest.approx(250.0 + 2 * junction)
    assert {lane.edge_id for lane in geometry.lanes.values() if not lane.on_highway} == {'Ramp_X', 'Ramp_Y'}


def rule_based_episode(override: dict, seed: int):
    """The neutral rule-based driver's episode on a scenario: its step results and metrics."""
    env = ExitDecisionEnv(load_project(scenario_override=override))
    try:
        results = []
        metrics = play_episode(env, rule_based(env), seed, lambda decision, info, *_: results.extend(info['step_results']))
        return results, metrics
    finally:
        env.close()


def as_shipped(results, rename=lambda edge: edge):
    """Each step's vehicles and arrivals, edges under their shipped names."""
    return [([(v.vehicle_id, rename(v.edge_id), v.lane_index, round(v.position, 6), round(v.speed, 6), v.on_highway,
               rename(v.route_target)) for v in r.vehicles],
             [(a.vehicle_id, rename(a.exit_edge), a.reached_target) for a in r.arrivals]) for r in results]


@pytest.fixture(scope='module')
def episodes():
    # seed 4: every exit is taken (HV3 by the first, CAVs and an HV2 by the target, HV1 and an HV2 by the end)
    return rule_based_episode(HALF, seed=4), rule_based_episode(RENAMED, seed=4)


def test_an_episode_on_the_renamed_road_is_the_episode_on_the_shipped_names(episodes):
    (shipped, shipped_metrics), (renamed, renamed_metrics) = episodes
    assert as_shipped(renamed, SHIPPED_NAME.get) == as_shipped(shipped)
    exits = {}
    for arrival in (a for r in renamed for a in r.arrivals):
        exits.setdefault(arrival.vehicle_class, set()).add(arrival.exit_edge)
    assert 'Ramp_Y' in exits['CAV'] and exits['HV3'] == {'Ramp_X'}
    assert renamed_metrics['p_CAV'] > 0
    for name in ('v_AVs', 'p_collision', 'N_braking', 'p_CAV', 'p_HV2', 'steps'):
        assert renamed_metrics[name] == shipped_metrics[name], name


def test_the_renamed_road_earns_the_same_reward(episodes):
    (_, shipped_metrics), (_, renamed_metrics) = episodes
    assert renamed_metrics['reward'] == shipped_metrics['reward']
