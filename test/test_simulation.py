"""The SUMO scenario through the libsumo wrapper (one simulation open at a time per process)."""
import math
import os

import pytest

from exit_decision.scenario.simulation import CommandError, HighwaySimulation
from exit_decision.traffic import CavCommand


def only(project_config, **counts):
    """The scenario with just the given vehicle classes: only(cfg, CAV=(1, lane))."""
    scenario = project_config.scenario
    classes = {}
    for name, cls in scenario.vehicle_classes.items():
        count, lane = counts.get(name, (0, cls.depart_lane))
        classes[name] = cls.model_copy(update={'count': count, 'depart_lane': lane,
                                               'insertion_probability': 1.0 if count else 0.0})
    return scenario.model_copy(update={'vehicle_classes': classes})


def run_until_empty(sim, seed, command_at=lambda result: {}):
    """Run an episode; command_at(result) gives the commands of each step. Returns all results."""
    result, results = sim.reset(seed), []
    while not (result.terminated or result.truncated):
        result = sim.step(command_at(result))
        results.append(result)
    return results


def exits_of(results):
    return {a.vehicle_id: a.exit_edge for r in results for a in r.arrivals}


def trace(results):
    return [(r.step, [(v.vehicle_id, v.lane_index, round(v.position, 6), round(v.speed, 6))
                      for v in r.vehicles]) for r in results]


def test_same_seed_same_episode_and_restart_in_one_process(project_config):
    with HighwaySimulation(project_config.scenario, cav_driver='policy') as sim:
        brake_then_go = lambda r: {v.vehicle_id: CavCommand(0, -1.0 if r.step % 40 < 20 else 1.0)
                                   for v in r.vehicles if v.controlled}
        first = trace(run_until_empty(sim, 7, brake_then_go))
        other = trace(run_until_empty(sim, 8, brake_then_go))
        again = trace(run_until_empty(sim, 7, brake_then_go))
    assert first == again
    assert first != other


def test_sumo_drivers_complete_every_route(project_config):
    with HighwaySimulation(project_config.scenario, cav_driver='sumo') as sim:
        results = run_until_empty(sim, 0)
    assert results[-1].terminated and results[-1].inserted == 60
    exits = exits_of(results)
    collided = {v for r in results for c in r.collisions for v in (c.collider, c.victim)}
    assert len(exits) + len(collided) == 60
    for vehicle_id, edge in exits.items():
        expected = {'HV1': {'Highway_2'}, 'HV3': {'Exit_0'}, 'CAV': {'Exit_1'},
                    'HV2': {'Exit_1', 'Highway_2'}}[vehicle_id.split('_')[0]]
        assert edge in expected, (vehicle_id, edge)


def test_commanded_acceleration_sets_the_speed_and_is_clipped(project_config):
    scenario = only(project_config, CAV=(1, 1))
    with HighwaySimulation(scenario, cav_driver='policy') as sim:
        sim.reset(0)
        cav = sim.step().vehicles[0]
        assert cav.controlled and cav.speed == pytest.approx(20.0)
        cav = sim.step({cav.vehicle_id: CavCommand(0, -8.0)}).vehicles[0]
        assert cav.speed == pytest.approx(20.0 - 0.8)
        assert cav.acceleration == pytest.approx(-8.0)
        for _ in range(40):   # the command is held: braking down to a stop, never below 0
            cav = sim.step().vehicles[0]
        assert cav.speed == 0.0
        for _ in range(70):   # 0 -> 30 m/s takes 60 steps at 5 m/s^2
            cav = sim.step({cav.vehicle_id: CavCommand(0, 5.0)}).vehicles[0]
        assert cav.speed == pytest.approx(scenario.vehicle_types['CAV'].max_speed)


def test_lane_changes_move_one_lane_and_never_off_the_road(project_config):
    with HighwaySimulation(only(project_config, CAV=(1, 2)), cav_driver='policy') as sim:
        sim.reset(0)
        cav = sim.step().vehicles[0]
        assert not sim.geometry.lane_change_exists(cav, +1)
        cav = sim.step({cav.vehicle_id: CavCommand(+1, 0.0)}).vehicles[0]
        assert cav.lane_index == 2 and cav.intention == 0, 'a change off the road is not made'
        cav = sim.step({cav.vehicle_id: CavCommand(-1, 0.0)}).vehicles[0]
        assert cav.lane_index == 1 and cav.intention == -1


@pytest.mark.parametrize('lane, right_after, expected_exit', [
    (0, None, 'Exit_0'),          # holds lane 0 past the end of Highway_0
    (2, None, 'Highway_2'),       # never in lane 0
    (1, 200.0, 'Exit_1'),         # moves to lane 0 after Exit_0, before Exit_1
])
def test_the_lane_held_at_a_diverge_picks_the_exit(project_config, lane, right_after, expected_exit):
    def command_at(result):
        return {v.vehicle_id: CavCommand(-1 if right_after and v.position > right_after and v.lane_index
                                         else 0, 0.0) for v in result.vehicles if v.controlled}
    with HighwaySimulation(only(project_config, CAV=(1, lane)), cav_driver='policy') as sim:
        results = run_until_empty(sim, 0, command_at)
    assert exits_of(results) == {'CAV_0': expected_exit}
    assert results[-1].terminated


@pytest.mark.parametrize('lane, missed_at', [(2, 'Highway_1'), (0, 'Highway_0')])
def test_a_cav_that_missed_exit_1_is_released_to_sumo_and_does_not_stand(project_config, lane, missed_at):
    """The step-cap case: a policy that brakes gently after the exit was missed held the
    road until the cap. Released to SUMO's driver, the CAV takes no more commands and drives
    off; the episode ends by itself."""
    def brake_once_missed(result):
        return {v.vehicle_id: CavCommand(0, -0.5 if v.position > 300.0 else 0.0)
                for v in result.vehicles if v.controlled}
    with HighwaySimulation(only(project_config, CAV=(1, lane)), cav_driver='policy') as sim:
        results = run_until_empty(sim, 0, brake_once_missed)
        states = [v for r in results for v in r.vehicles]
        released_at = next(v for v in states if not v.controlled)
        assert released_at.edge_id in (missed_at, 'Highway_2', 'Exit_0')
        assert results[-1].terminated and not results[-1].truncated, 'no standstill until the step cap'
    assert all(not v.controlled for v in states if v.position > released_at.position)
    assert 'CAV_0' in results[-1].released
    assert exits_of(results)['CAV_0'] != 'Exit_1'


def test_a_released_cav_takes_no_command(project_config):
    with HighwaySimulation(only(project_config, CAV=(1, 2)), cav_driver='policy') as sim:
        result = sim.reset(0)
        while not any(not v.controlled for v in result.vehicles):
            result = sim.step({v.vehicle_id: CavCommand(0, 0.0) for v in result.vehicles if v.controlled})
        with pytest.raises(CommandError, match='does not control'):
            sim.step({'CAV_0': CavCommand(0, -8.0)})


def test_hv2_moves_right_when_clear_and_takes_exit_1(project_config):
    with HighwaySimulation(only(project_config, HV2=(1, 2)), cav_driver='policy') as sim:
        results = run_until_empty(sim, 0)
    lanes = [v.lane_index for r in results for v in r.vehicles if v.edge_id.startswith('Highway')]
    assert lanes[0] == 2 and 0 in lanes
    assert exits_of(results) == {'HV2_0': 'Exit_1'}


def test_bad_commands_are_refused_with_the_reason(project_config):
    with HighwaySimulation(only(project_config, CAV=(1, 1), HV1=(1, 0)), cav_driver='policy') as sim:
        sim.reset(0)
        result = sim.step()
        ids = {v.vehicle_class: v.vehicle_id for v in result.vehicles}
        with pytest.raises(CommandError, match="unknown vehicle 'CAV_99'"):
            sim.step({'CAV_99': CavCommand(0, 0.0)})
        with pytest.raises(CommandError, match='acceleration must be finite'):
            sim.step({ids['CAV']: CavCommand(0, math.nan)})
        with pytest.raises(CommandError, match='does not control'):
            sim.step({ids['HV1']: CavCommand(0, 0.0)})
        with pytest.raises(CommandError, match='lane_change must be'):
            sim.step({ids['CAV']: CavCommand(2, 0.0)})
        assert sim.step({ids['CAV']: CavCommand(0, 1.0)}).step == result.step + 1


def test_collisions_are_real_and_reported(project_config):
    """CAVs that hold 20 m/s with SUMO's safety off run into slower traffic."""
    with HighwaySimulation(project_config.scenario, cav_driver='policy') as sim:
        results = run_until_empty(sim, 0)
    collisions = [c for r in results for c in r.collisions]
    assert any(c.involves_cav for c in collisions)
    for index, result in enumerate(results):
        for c in result.collisions:   # colliders are removed from the road
            later = {v.vehicle_id for r in results[index:] for v in r.vehicles}
            assert c.collider not in later and c.victim not in later


def test_sumo_tools_are_found_without_the_venv_on_path(monkeypatch):
    """`.venv/bin/exit-decision` called directly: netconvert comes from the installed package."""
    from exit_decision.scenario.sumo_inputs import sumo_tool
    monkeypatch.setenv('PATH', '/usr/bin:/bin')
    path = sumo_tool('netconvert')
    assert path.endswith('/bin/netconvert') and os.access(path, os.X_OK)
