"""Short training runs end to end: finite losses, checkpoints chosen against the teacher,
the conditioned network evaluated at every mode, resume."""
import csv
import json
import math

import pytest

from exit_decision.config import load_project
from exit_decision.evaluation.report import evaluate_runs, read_summary
from exit_decision.learning.trainer import Trainer
from exit_decision.learning.validation import INFEASIBLE, selection_score
from exit_decision.errors import PolicyError
from exit_decision.model.policy import load_policy

from ros_helpers import small_config_dir

TINY = {'training': {'warmup_decisions': 10, 'replay_size': 2000, 'batch_size': 8,
                     'demonstrations': {'episodes': 1, 'pretrain_updates': 20},
                     'validation': {'every_episodes': 2, 'episodes': 1, 'parallel': False}}}


@pytest.fixture(scope='module')
def config_dir(tmp_path_factory):
    return small_config_dir(tmp_path_factory.mktemp('cfg') / 'config')


def rows(path):
    with open(path, newline='') as stream:
        return list(csv.DictReader(stream))


def test_conditioned_training_run_and_its_evaluation_at_every_mode(config_dir, tmp_path):
    config = load_project(config_dir, overrides=[TINY])
    trainer = Trainer(config, 'mdgqn', 'conditioned', 0, tmp_path / 'run')
    assert trainer.collector.demonstrator.choose.__self__.parameters == config.env.rule_based, 'one neutral teacher'
    policy_path = trainer.run(episodes=2, progress=False)
    log = rows(tmp_path / 'run' / 'training.csv')
    assert len(log) == 2 and all(math.isfinite(float(row['loss'])) for row in log)
    validation = rows(tmp_path / 'run' / 'validation.csv')
    assert [(int(r['episode']), r['mode']) for r in validation] == [
        (e, m) for e in (0, 2) for m in ('AGGI', 'AGGP', 'CONI', 'CONP')], 'after pre-training and episode 2'
    policy = load_policy(policy_path)
    assert policy.conditioned and policy.metadata['mode'] == 'conditioned'
    evaluate_runs(config, [policy_path], ['rule_based'], ['AGGI', 'CONP'], episodes=1, seed=10_000,
                  out_dir=tmp_path / 'eval', command='test')
    names = {p.name for p in (tmp_path / 'eval').iterdir()}
    assert {'rule_based_AGGI.csv', 'rule_based_CONP.csv', 'mdgqn_conditioned_AGGI.csv',
            'mdgqn_conditioned_CONP.csv', 'comparison.md'} <= names
    summary = read_summary(tmp_path / 'eval' / 'summary.csv')
    teacher = {m: float(rows(tmp_path / 'eval' / f'rule_based_{m}.csv')[0]['reward']) for m in ('AGGI', 'CONP')}
    assert teacher['AGGI'] != teacher['CONP'], 'one teacher episode, scored under each mode'
    assert 0.0 <= summary['mdgqn_conditioned_AGGI']['p_CAV'][0] <= 1.0


def test_selection_prefers_the_smallest_gain_among_safe_candidates():
    safe = {'p_CAV': 1.0, 'p_collision_CAV': 0.0, 'capped': 0.0}
    good = selection_score({'AGGI': {**safe, 'gain': 0.3}, 'CONP': {**safe, 'gain': 0.1}}, 0.99, 0.0067)
    worse = selection_score({'AGGI': {**safe, 'gain': 0.5}, 'CONP': {**safe, 'gain': 0.05}}, 0.99, 0.0067)
    unsafe = selection_score({'AGGI': {**safe, 'gain': 2.0}, 'CONP': {**safe, 'gain': 2.0, 'p_CAV': 0.95}},
                             0.99, 0.0067)
    assert good == pytest.approx(0.1) and worse < good
    assert unsafe < INFEASIBLE < worse


def test_training_resumes_from_its_last_state(config_dir, tmp_path):
    config = load_project(config_dir, overrides=[TINY])
    Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run').run(episodes=2, progress=False)
    trainer = Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run')
    trainer.run(episodes=3, resume=tmp_path / 'run' / 'last.pt', progress=False)
    assert [int(r['episode']) for r in rows(tmp_path / 'run' / 'training.csv')] == [0, 1, 2]
    assert {r['mode'] for r in rows(tmp_path / 'run' / 'validation.csv')} == {'CONP'}
    with pytest.raises(FileExistsError, match='holds an earlier run'):
        Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run').run(episodes=3, progress=False)
    with pytest.raises(ValueError, match='a gqn/CONP run, not mdgqn/CONP'):
        Trainer(config, 'mdgqn', 'CONP', 0, tmp_path / 'other').checkpoints.load_state(tmp_path / 'run' / 'last.pt')


def test_a_resumed_run_validates_the_candidates_its_stop_left_unvalidated(config_dir, tmp_path):
    config = load_project(config_dir, overrides=[TINY])
    Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run').run(episodes=2, progress=False)
    log = tmp_path / 'run' / 'validation.csv'
    lines = log.read_text().splitlines()
    kept = [lines[0]] + [line for line in lines[1:] if line.startswith('0,')]
    log.write_text('\n'.join(kept) + '\n')   # stopped while the episode-2 candidate was being validated
    assert [int(r['episode']) for r in rows(log)] == [0]
    Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run').run(episodes=2, resume=tmp_path / 'run' / 'last.pt',
                                                          progress=False)
    assert [int(r['episode']) for r in rows(log)] == [0, 2], 'validated once, no episode trained again'
    assert len(rows(tmp_path / 'run' / 'training.csv')) == 2


def test_a_budget_of_environment_steps_ends_training_and_runs_the_schedules_in_steps(config_dir, tmp_path):
    steps = 150
    budget = {'training': {'environment_steps': steps, 'exploration': {'epsilon_decay_steps': steps},
                           'demonstrations': {'margin_decay_steps': 2 * steps}}}
    config = load_project(config_dir, overrides=[TINY, budget])
    Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run').run(episodes=1000, progress=False)
    log = rows(tmp_path / 'run' / 'training.csv')
    decisions = [int(r['decisions']) for r in log]
    assert decisions[-1] >= steps > decisions[-2], 'ends with the episode that reaches the budget, not at 1000'
    e, d = config.training.exploration, config.training.demonstrations
    # epsilon: the episode's, from the decisions before it; the margin weight: at the episode's end
    for row, before, after in zip(log, [0, *decisions[:-1]], decisions):
        assert float(row['epsilon']) == pytest.approx(e.epsilon_start + (e.epsilon_end - e.epsilon_start) * before / steps)
        assert float(row['margin_weight']) == pytest.approx(
            d.margin_weight_start + (d.margin_weight_end - d.margin_weight_start) * min(after / (2 * steps), 1.0))
    timing = json.loads((tmp_path / 'run' / 'timing.json').read_text())
    assert (timing['episodes'], timing['decisions']) == (len(log), decisions[-1])


def test_training_can_start_from_a_policy_network_without_pre_training(config_dir, tmp_path):
    import torch
    config = load_project(config_dir, overrides=[TINY])
    first = Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'first')
    start = first.run(episodes=0, progress=False)       # pre-trained, validated: policy.pt
    trainer = Trainer(config, 'gqn', 'CONP', 1, tmp_path / 'second')
    trainer.pretrain = lambda: pytest.fail('a run started from --init must not pre-train')
    trainer.run(episodes=0, init=start, progress=False)
    ours, theirs = load_policy(tmp_path / 'second' / 'policy.pt'), load_policy(start)
    for key, value in theirs.network.state_dict().items():
        assert torch.equal(ours.network.state_dict()[key], value), key
    with pytest.raises(PolicyError, match='is not this run'):
        Trainer(config, 'mdgqn', 'conditioned', 0, tmp_path / 'third').checkpoints.load_network(start)


def test_train_refuses_episodes_when_the_config_budgets_environment_steps(config_dir, tmp_path, capsys):
    from exit_decision.cli import main
    override = tmp_path / 'steps.yaml'
    override.write_text('training: {environment_steps: 100}\n')
    assert main(['train', '--config-dir', str(config_dir), '--override', str(override), '--algorithm', 'gqn',
                 '--conditioning', 'CONP', '--episodes', '3', '--out', str(tmp_path / 'run')]) == 2
    assert "--episodes 3: this config's budget for gqn is environment_steps: 100" in capsys.readouterr().err
    assert not (tmp_path / 'run').exists()


def test_conditioned_training_over_options_and_its_checkpoint(config_dir, tmp_path):
    """Issue 28: the same loop over options: every CAV row acts with the option it holds, a row
    whose option goes on bootstraps on it; the checkpoint says its action space, evaluation
    drives it through the low level, and a grid-only caller refuses it in one line."""
    from exit_decision.agents.options import OptionSpace
    from exit_decision.env import ExitDecisionEnv
    from exit_decision.model.policy import load_controller

    config = load_project(config_dir, overrides=[TINY])
    trainer = Trainer(config, 'mdgqn', 'conditioned', 0, tmp_path / 'run', action_space='options')
    transitions = trainer.collector.episode(800_000)   # the demonstrator
    neutral = trainer.env.options.index('route', 'neutral')
    acted = [t.actions[t.actions >= 0] for t in transitions]
    assert all((a == neutral).all() for a in acted), 'the demonstrator: the neutral style, the route plan'
    assert any(t.continuing.any() for t in transitions) and any((~t.continuing & (t.actions >= 0)).any()
                                                                for t in transitions)
    policy_path = trainer.run(episodes=2, progress=False)
    policy = load_policy(policy_path)
    assert policy.action_space == 'options' and policy.network.shape.num_actions == trainer.env.options.size
    from exit_decision.driving.prior import PriorTable
    prior = PriorTable.from_metadata(policy.prior)
    assert list(prior.vectors) == list(config.env.options.styles) and len(prior.seeds) == config.training.validation.episodes, \
        'an options policy carries the prior measured on the validation seeds'
    evaluate_runs(config, [policy_path], [], ['AGGI'], episodes=1, seed=10_000, out_dir=tmp_path / 'eval',
                  command='test')
    assert 0.0 <= read_summary(tmp_path / 'eval' / 'summary.csv')['mdgqn_options_conditioned_AGGI']['p_CAV'][0] <= 1.0
    from exit_decision.experiments.constant_options import neutral_run, run_table, table_markdown
    variant = config.env.reward_variant
    text = table_markdown(run_table(config, [10_000, 10_001], [variant], 1, {'learned': policy_path}), ['AGGI', 'CONP'],
                          variant, neutral_run(config))
    assert '| policy | mode |' in text and '\n| learned | AGGI |' in text and '\n| learned | CONP |' in text, 'judged per mode'
    env = ExitDecisionEnv(config)
    try:
        with pytest.raises(PolicyError, match='a policy over options; this command runs policies over grid only'):
            load_controller(config, policy_path, env.shield, env.planner)
        assert OptionSpace(config, env.shield, env.planner).size == trainer.env.options.size
    finally:
        env.close()
