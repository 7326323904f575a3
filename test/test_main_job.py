"""What the main job prints at its end, from made-up figures: the README's metric names and
units, no spread for one episode, one verdict line against the same seed without the switch,
one consistency line, where the switch landed and why, and the next steps."""
from pathlib import Path

from exit_decision.evaluation.main_job import (SwitchTiming, consistency_line, metrics_lines, next_lines,
                                               returns_line, timing_line, verdict_line)
from exit_decision.evaluation.switch import WindowFigures
from exit_decision.ros.bags.switch import RecordedSwitch, SwitchOutcome

EPISODE = {'v_AVs': 16.784, 'v_s': 18.53, 'p_collision': 0.0, 'p_collision_CAV': 0.0, 'N_braking': 6.0,
           'braking_steps': 22.0, 'p_CAV': 1.0, 'p_HV2': 0.8, 'reward': 6.841, 'steps': 770.0}


def outcome(bag_after: WindowFigures | None = None) -> SwitchOutcome:
    before = WindowFigures(18.43, 1.81, 0, 10)
    switched, kept = WindowFigures(16.80, 1.85, 0, 10), WindowFigures(17.31, 1.74, 2, 10)
    return SwitchOutcome(RecordedSwitch(0, 305, 30.5, 'AGGP', 'CONP', []), 10000, 10.0,
                         (before, bag_after or switched), (before, switched), (before, kept), (1.96, 5.12), 770)


def test_one_episode_is_its_values_in_the_readmes_words_without_a_spread():
    text = '\n'.join(metrics_lines([EPISODE], -4.5))
    assert '±' not in text
    for name in ('Exit-1 rate', 'CAV collisions', 'Speed', 'Hard brakings'):
        assert name in text
    assert '16.78 m/s' in text and '18.53 m/s' in text and '4.5 m/s²' in text
    for column in ('v_AVs', 'v_s', 'p_HV2', 'braking_steps', 'N_braking', 'p_CAV'):
        assert column not in text, f'a raw column name: {column}'


def test_several_episodes_are_a_mean_and_spread():
    text = '\n'.join(metrics_lines([EPISODE, {**EPISODE, 'v_AVs': 14.784, 'steps': 700.0}], -4.5))
    assert '2 episodes' in text and '15.78 ± 1.00 m/s' in text


def test_the_verdict_is_one_line_naming_what_the_switch_changed_against_the_same_seed_without_it():
    line = verdict_line(outcome())
    assert '\n' not in line and line.startswith('verdict: switching to CONP')
    assert 'slower' in line and 'longer time headways' in line and 'fewer hard brakings' in line
    assert '16.80 against 17.31 m/s (-0.51)' in line and 'in AGGP throughout' in line


def test_the_bag_and_the_environment_are_one_consistency_line_that_fails_when_they_differ():
    assert consistency_line(outcome()).startswith('consistency check: ')
    failed = consistency_line(outcome(WindowFigures(16.26, 1.85, 0, 10)))
    assert failed.startswith('consistency check FAILED') and '16.80 against 16.26 m/s' in failed
    assert '\n' not in failed


def test_the_switch_says_where_it_landed_and_why_later_and_each_modes_return():
    line = timing_line('AGGP', 'CONP', SwitchTiming(300, 301, 305, 5, 0.1))
    assert 'asked for at step 300, requested at step 301, in force from step 305 (30.5 s)' in line
    assert 'every 5 steps' in line and 'set_parameters' in line
    returns = returns_line(outcome())
    assert "AGGP's weights for steps 0-304" in returns and '1.96' in returns
    assert "CONP's weights for steps 305-770" in returns and '5.12' in returns


def test_the_next_steps_name_the_bag_and_the_logs():
    text = '\n'.join(next_lines(Path('bags/b'), Path('runs/stack_logs/t')))
    assert 'exit-decision show bags/b' in text and 'ros2 bag info bags/b' in text and 'runs/stack_logs/t/' in text
