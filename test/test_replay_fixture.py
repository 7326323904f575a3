"""Replay as a regression test: the fixture bag the stack recorded (test/fixtures/replay_bag) is
decided again by the shipped policy, shield, lane planner and graph builder, command for command.
A change that alters a decision fails here, naming the first one; when the change is on purpose,
record the fixture again with `exit-decision fixture record` (README, "Command line")."""
from pathlib import Path

import pytest

from exit_decision.config import load_project
from exit_decision.errors import PolicyError
from exit_decision.model.names import policy_path
from exit_decision.ros.bags.storage import read_messages
from exit_decision.ros.topics import COMMANDS_TOPIC
from exit_decision.ros.bags.replay import check_fixture, replay_decisions

FIXTURE = Path(__file__).parent / 'fixtures' / 'replay_bag'
RE_RECORD = 'if the change is meant, record the fixture again: exit-decision fixture record'


def test_every_recorded_command_is_decided_again():
    report = check_fixture(FIXTURE)
    assert report.decisions > 0 and not report.missing_inputs and not report.custom_weights, report.summary(limit=0)
    assert not report.differences, (f'{len(report.differences)} of {report.commands} recorded commands are decided '
                                    f'otherwise; the first: {report.differences[0]} ({RE_RECORD})')
    assert report.reproduced


def test_the_fixture_covers_both_modes_of_a_switch():
    modes = [msg.mode for _, _, _, msg in read_messages(FIXTURE / 'bag', {COMMANDS_TOPIC})]
    assert modes[0] != modes[-1] and set(modes) == {modes[0], modes[-1]}, 'one switch: decisions in two modes'


def test_a_changed_decision_fails_the_replay_naming_the_first_difference():
    """The check can fail: with the lane planner off, the shipped policy decides otherwise somewhere."""
    report = check_fixture(FIXTURE, overrides=[{'env': {'lane_planner': False}}])
    assert not report.reproduced and report.differences
    first = report.differences[0]
    assert first.startswith('episode 0 step ') and ': recorded (' in first and ', replayed (' in first, first


def test_a_per_mode_policy_refuses_the_other_modes_decisions_in_one_line(per_mode_policies):
    """The fixture switches AGGP -> CONP: a per-mode policy of AGGP, given instead, decides the
    AGGP part and refuses at the first CONP decision, instead of deciding it as AGGP."""
    config = load_project(None, overrides=[FIXTURE / 'override.yaml'])
    per_mode = policy_path(per_mode_policies, 'gqn', 'AGGP')
    with pytest.raises(PolicyError, match=r"a policy of mode 'AGGP' decides for that mode only, not for mode 'CONP' \(weights \["):
        replay_decisions(FIXTURE / 'bag', config, per_mode_policies, policy_file=per_mode, rebuild_graph=True)
