"""A short training run end to end: finite losses, a checkpoint that evaluates, resume."""
import csv
import math

import pytest

from exit_decision.config import load_project
from exit_decision.evaluation.report import evaluate_runs, read_summary
from exit_decision.learning.trainer import Trainer
from exit_decision.policy import load_policy

from ros_helpers import small_config_dir

TINY = {'training': {'warmup_decisions': 10, 'replay_size': 2000,
                     'demonstrations': {'episodes': 1, 'pretrain_updates': 20},
                     'validation': {'every_episodes': 2, 'episodes': 1}}}


@pytest.fixture(scope='module')
def config_dir(tmp_path_factory):
    return small_config_dir(tmp_path_factory.mktemp('cfg') / 'config')


def rows(path):
    with open(path, newline='') as stream:
        return list(csv.DictReader(stream))


def test_short_training_run_gives_finite_losses_and_an_evaluable_policy(config_dir, tmp_path):
    own_demonstrator = {'modes': {'modes': {'AGGI': {'rule_based': {'time_headway': 0.9}}}}}
    config = load_project(config_dir, overrides=[TINY, own_demonstrator])
    trainer = Trainer(config, 'mdgqn', 'AGGI', 0, tmp_path / 'run')
    assert trainer.demonstrator.parameters.time_headway == 0.9, "the mode's demonstrator, not env.yaml's"
    policy_path = trainer.run(episodes=2, progress=False)
    log = rows(tmp_path / 'run' / 'training.csv')
    assert len(log) == 2
    assert all(math.isfinite(float(row['loss'])) for row in log)
    assert len(rows(tmp_path / 'run' / 'validation.csv')) == 2, 'after pre-training and after episode 2'
    policy = load_policy(policy_path)
    assert policy.metadata['algorithm'] == 'mdgqn' and policy.metadata['mode'] == 'AGGI'
    assert policy.metadata['multi_step'] == 3
    evaluate_runs(config, [policy_path], ['rule_based', 'rule_based:AGGI'], episodes=1, seed=10_000,
                  out_dir=tmp_path / 'eval', command='test')
    summary = read_summary(tmp_path / 'eval' / 'summary.csv')
    assert set(summary) == {'rule_based', 'rule_based_AGGI', 'mdgqn_AGGI'}
    assert 0.0 <= summary['mdgqn_AGGI']['p_CAV'][0] <= 1.0
    assert (tmp_path / 'eval' / 'mdgqn_AGGI_actions.csv').exists()


def test_training_resumes_from_its_last_state(config_dir, tmp_path):
    config = load_project(config_dir, overrides=[TINY])
    Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run').run(episodes=2, progress=False)
    trainer = Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run')
    trainer.run(episodes=3, resume=tmp_path / 'run' / 'last.pt', progress=False)
    assert [int(r['episode']) for r in rows(tmp_path / 'run' / 'training.csv')] == [0, 1, 2]
    with pytest.raises(FileExistsError, match='holds an earlier run'):
        Trainer(config, 'gqn', 'CONP', 0, tmp_path / 'run').run(episodes=3, progress=False)
    with pytest.raises(ValueError, match='a gqn/CONP run, not mdgqn/CONP'):
        Trainer(config, 'mdgqn', 'CONP', 0, tmp_path / 'other').load_state(tmp_path / 'run' / 'last.pt')
