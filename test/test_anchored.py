"""An anchored policy (issue 39): training runs' networks in one checkpoint with their prior,
departing from the prior's option only where their lower confidence bound beats a margin; the
stack, evaluation and validation drive it through the one policy driver (``driving.policy``)."""
from pathlib import Path

import pytest

from exit_decision.driving.anchored import Anchor
from exit_decision.errors import PolicyError
from exit_decision.learning.anchoring import anchor_policy
from exit_decision.model.policy import load_policy

POLICIES = Path(__file__).resolve().parent.parent / 'policies'
#: a conditioned policy over options that carries its prior (the probe of issue 39)
MEMBER = POLICIES / 'probes' / 'mdgqn_options_conditioned_traffic' / 'policy.pt'


def test_an_anchored_policy_drives_as_its_members_at_no_margin_and_as_its_prior_past_every_gain(tmp_path,
                                                                                               project_config):
    from exit_decision.agents.options import OptionSpace
    from exit_decision.driving.prior import PriorDriver, PriorTable
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.evaluation.evaluate import evaluate_policy, play_episodes, scored_episodes
    from exit_decision.model.modes import ModeWeights

    greedy = anchor_policy([MEMBER, MEMBER], Anchor(kappa=0.0, margin=0.0), tmp_path / 'greedy.pt')
    fallback = anchor_policy([MEMBER, MEMBER], Anchor(kappa=1.0, margin=1e6), tmp_path / 'fallback.pt')
    assert len(load_policy(greedy).members) == 2
    env, seeds = ExitDecisionEnv(project_config), [31, 32]
    try:
        member, = evaluate_policy(env, MEMBER, ['CONI'], seeds)
        as_member, = evaluate_policy(env, greedy, ['CONI'], seeds)
        as_prior, = evaluate_policy(env, fallback, ['CONI'], seeds)
        table = PriorTable.from_metadata(load_policy(MEMBER).prior)
        prior = play_episodes(env, PriorDriver(table, OptionSpace(project_config, env.shield, env.planner),
                                               ModeWeights(project_config).mode('CONI')), seeds)
        weights = env.reward_fn.weights(project_config.mode('CONI'))
    finally:
        env.close()
    assert [e['reward'] for e in as_member.episodes] == [e['reward'] for e in member.episodes]
    assert as_member.result.departures == member.result.departures > 0, 'the member departs from its prior'
    assert as_prior.result.departures == 0 < as_prior.result.choices
    prior = scored_episodes(prior, weights)
    assert [e['reward'] for e in as_prior.episodes] == [e['reward'] for e in prior], 'it drives as its prior'


def test_members_that_do_not_fit_together_are_refused_naming_the_file(tmp_path):
    grid = POLICIES / 'mdgqn_conditioned' / 'policy.pt'
    with pytest.raises(PolicyError, match='mdgqn_conditioned'):
        anchor_policy([MEMBER, grid], Anchor(0.0, 0.0), tmp_path / 'p.pt')


def test_the_anchor_command_validates_every_point_and_keeps_the_best(tmp_path, capsys):
    import json

    from exit_decision.cli import main
    from exit_decision.tables import read_rows

    out = tmp_path / 'anchored'
    assert main(['anchor', '--policy', str(MEMBER), '--policy', str(MEMBER), '--kappa', '0', '--margin', '0',
                 '--margin', '1e6', '--episodes', '1', '--out', str(out)]) == 0
    rows = read_rows(out / 'anchor.csv')
    assert len(rows) == 8 and {row['mode'] for row in rows} == {'AGGI', 'AGGP', 'CONI', 'CONP'}
    assert all(float(row['departures']) == 0.0 for row in rows if float(row['margin']) == 1e6)
    chosen = json.loads((out / 'anchor.json').read_text())
    assert chosen['command'].startswith('exit-decision anchor') and chosen['validation_seeds'] == [900000]
    best = max(rows, key=lambda row: float(row['score']))
    assert chosen['chosen'] == {'kappa': 0.0, 'margin': float(best['margin'])}
    assert load_policy(out / 'policy.pt').metadata['anchor'] == chosen['chosen']
    assert 'departures from the prior' in capsys.readouterr().out
