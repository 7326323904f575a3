"""Collection on Ray actors (issue 38): ``train --actors N`` runs the same episodes on N actor
processes, learns here, broadcasts its weights, survives an actor that dies, and refuses bad values."""
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from exit_decision.config import load_project
from exit_decision.learning.trainer import Trainer
from exit_decision.model.policy import load_policy
from ros_helpers import small_config_dir
from test_training import TINY, rows

#: a few short episodes, updates from the actors' first transitions on, weights sent after every 5 updates
ACTORS = {'training': {**TINY['training'], 'warmup_decisions': 5, 'actors': {'broadcast_every': 5, 'max_restarts': 1}}}


@pytest.fixture(scope='module')
def config(tmp_path_factory):
    return load_project(small_config_dir(tmp_path_factory.mktemp('cfg') / 'config'), overrides=[ACTORS])


def test_two_actors_collect_the_learner_updates_broadcasts_and_checkpoints(config, tmp_path):
    trainer = Trainer(config, 'mdgqn', 'conditioned', 0, tmp_path / 'run', action_space='options')
    initial = {key: value.clone() for key, value in trainer.agent.online.state_dict().items()}
    policy_path = trainer.run(episodes=4, progress=False, actors=2)
    log = rows(tmp_path / 'run' / 'training.csv')
    assert len(log) == 4 and {row['actor'] for row in log} == {'0', '1'}, 'both actors played'
    assert int(log[-1]['updates']) > 0 and max(int(row['weights_age']) for row in log) >= 0
    epsilons = {row['actor']: float(row['epsilon']) for row in log}
    assert epsilons['1'] < epsilons['0'], 'each actor its own exploration rate'
    assert trainer.actor_counts.restarts == 0 and not trainer.actor_counts.dropped
    last = torch.load(tmp_path / 'run' / 'last.pt', weights_only=True)['online']
    assert any(not torch.equal(last[key], initial[key]) for key in initial), 'the learner learnt from the actors'
    assert load_policy(policy_path).action_space == 'options'


def test_an_actor_that_dies_is_restarted_and_the_run_ends_with_a_checkpoint(config, tmp_path, monkeypatch):
    from exit_decision.learning import actors

    killed = []
    episodes = actors.ActorPool.episodes

    def kill_one_then_collect(pool, next_task):
        for finished in episodes(pool, next_task):
            if not killed:
                pid = pool.pids()[0]
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
            yield finished
    monkeypatch.setattr(actors.ActorPool, 'episodes', kill_one_then_collect)
    trainer = Trainer(config, 'mdgqn', 'conditioned', 1, tmp_path / 'run', action_space='options')
    trainer.run(episodes=4, progress=False, actors=2)
    assert killed and len(rows(tmp_path / 'run' / 'training.csv')) == 4, 'every episode of the budget was played'
    counts = trainer.actor_counts
    assert counts.restarts + len(counts.dropped) >= 1, f'the death was counted: {counts}'
    assert not counts.dropped, f'one death, within the restart limit: {counts}'
    assert (tmp_path / 'run' / 'last.pt').is_file()


@pytest.mark.parametrize('arguments, expected', [
    (['--actors', '-1'], '--actors'),
    (['--actors', 'two'], '--actors'),
    (['--actors', '1', '--address', '127.0.0.1:1'], 'no Ray cluster listening there'),
])
def test_bad_actor_options_give_one_line_and_exit_code_2(tmp_path, arguments, expected):
    started = time.monotonic()
    result = subprocess.run([sys.executable, '-m', 'exit_decision', 'train', '--out', str(tmp_path / 'run'), *arguments],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and expected in result.stderr and 'Traceback' not in result.stderr, result.stderr
    assert time.monotonic() - started < 30


@pytest.fixture(scope='module')
def ray_cluster(tmp_path_factory):
    """A Ray cluster as a user starts one (`ray start --head`), on loopback, stopped at the end."""
    import socket
    with socket.socket() as probe:
        probe.bind(('127.0.0.1', 0))
        port = probe.getsockname()[1]
    ray = os.path.join(os.path.dirname(sys.executable), 'ray')
    env = {**os.environ, 'RAY_USAGE_STATS_ENABLED': '0', 'RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER': '0'}
    started = subprocess.run([ray, 'start', '--head', f'--port={port}', '--node-ip-address=127.0.0.1', '--num-cpus=2',
                              '--include-dashboard=false', '--disable-usage-stats'], env=env, capture_output=True,
                             text=True, timeout=120)
    assert started.returncode == 0, started.stderr
    try:
        yield f'127.0.0.1:{port}'
    finally:
        subprocess.run([ray, 'stop', '--force'], env=env, capture_output=True, timeout=120)


def test_train_with_actors_joins_a_running_cluster_and_its_checkpoint_learnt(ray_cluster, tmp_path):
    import yaml
    config_dir = small_config_dir(tmp_path / 'config')
    override = tmp_path / 'actors.yaml'
    override.write_text(yaml.safe_dump({'training': ACTORS['training']}))
    out = tmp_path / 'run'
    result = subprocess.run([sys.executable, '-m', 'exit_decision', 'train', '--config-dir', str(config_dir),
                             '--override', str(override), '--action-space', 'options', '--episodes', '3',
                             '--actors', '2', '--address', ray_cluster, '--out', str(out)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert '2 actors: 0 episode(s) given again' in result.stdout
    log = rows(out / 'training.csv')
    assert len(log) == 3 and int(log[-1]['updates']) > 0, 'the learner updated from the actors\' transitions'
    initial = torch.load(out / 'candidates' / 'episode_00000.pt', weights_only=True)['state_dict']
    last = torch.load(out / 'last.pt', weights_only=True)['online']
    assert any(not torch.equal(last[key], initial[key]) for key in initial), 'the weights moved'


def test_the_comparison_sweep_joins_a_running_cluster(ray_cluster, tmp_path):
    from exit_decision.experiments.compare import Job, SweepResult, run_on_ray

    def where() -> int:   # nested: Ray ships it by value
        import os
        return os.getpid()

    got = []
    result = run_on_ray([Job('where', where, (), got.append)], SweepResult(cells=1), ray_cluster, None, 0, False)
    assert result.done == 1 and got and got[0] != os.getpid(), 'the task ran in a worker of the cluster'
