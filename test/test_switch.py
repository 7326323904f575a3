"""The figures the main job prints around a mode switch, from hand-made steps."""
import math

import pytest

from exit_decision.evaluation.switch import switch_windows

from conftest import make_vehicle


def test_before_and_after_the_switch_for_the_cavs_on_the_road_at_it():
    steps = []
    for k in range(200):                       # 20 s at 0.1 s, the switch at 10 s
        time = k * 0.1
        after = time >= 10.0
        speed = 15.0 if after else 20.0
        cav = make_vehicle('cav', 'CAV', position=100.0 + k, speed=speed,
                           acceleration=-5.0 if k in (50, 51, 150) else 0.0)
        leader = make_vehicle('lead', 'HV1', position=100.0 + k + 5.0 + (30.0 if after else 20.0), speed=speed)
        vehicles = [cav, leader]
        if k > 120:                            # a CAV that entered after the switch is not followed
            vehicles.append(make_vehicle('late', 'CAV', lane=1, position=0.0, speed=1.0, acceleration=-9.0))
        steps.append((time, vehicles))
    before, after = switch_windows(steps, switch_time=10.0)
    assert before.cavs == after.cavs == 1
    assert before.speed == pytest.approx(20.0) and after.speed == pytest.approx(15.0)
    assert before.headway == pytest.approx(20.0 / 20.0) and after.headway == pytest.approx(30.0 / 15.0)
    assert before.hard_brakings == 1 and after.hard_brakings == 1, 'a run of steps counts once, the late CAV never'


def test_no_leader_in_range_gives_no_headway():
    steps = [(k * 0.1, [make_vehicle('cav', 'CAV', speed=20.0)]) for k in range(40)]
    before, after = switch_windows(steps, switch_time=2.0, window=2.0)
    assert math.isnan(before.headway) and math.isnan(after.headway) and before.speed == 20.0


def test_the_stack_shows_the_recorded_switch_beside_the_same_seed_without_it():
    """On the replay fixture (the shipped stack, AGGP -> CONP half-way): the outcome names the
    switch, and the environment's runs of the same seed with and without it are the same
    driving before it (like for like), so the figures after it tell what the switch did: the
    CAVs on the road at it slow down and keep longer gaps than without it. The returns are each
    mode's for the part of the episode it drove, to the episode's end."""
    import math
    from pathlib import Path

    from exit_decision.config import load_project
    from exit_decision.model.names import default_policy_dir
    from exit_decision.ros.bags.replay import FIXTURE_RUN
    from exit_decision.ros.bags.switch import recorded_switch, switch_outcome

    fixture = Path(__file__).parent / 'fixtures' / 'replay_bag'
    config = load_project(None, overrides=[fixture / 'override.yaml'])
    switch = recorded_switch(fixture / 'bag', config)
    assert (switch.before, switch.after) == ('AGGP', 'CONP') and switch.step >= FIXTURE_RUN['switch_at_step']
    outcome = switch_outcome(fixture / 'bag', config, default_policy_dir(), FIXTURE_RUN['algorithm'],
                             FIXTURE_RUN['seed'])
    assert outcome.switch == switch and outcome.seed == FIXTURE_RUN['seed']
    assert outcome.switched[0] == outcome.kept[0], 'the same driving before the switch'
    (_, switched), (_, kept) = outcome.switched, outcome.kept
    assert switched.speed < kept.speed and switched.headway > kept.headway, \
        f'slower, with longer gaps, than the same seed without the switch: {switched}, {kept}'
    assert switch.step < outcome.last_step <= config.scenario.max_steps
    assert all(math.isfinite(value) for value in outcome.returns)
