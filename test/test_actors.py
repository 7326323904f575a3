"""Collection on Ray actors (issue 38): ``train --actors N`` runs the same episodes on N actor
processes, learns here, broadcasts its weights, survives an actor that dies, and refuses bad values."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

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
        pids = pool.pids()   # asked before: an actor answers between episodes only
        for finished in episodes(pool, next_task):
            if not killed:   # the actor that finished has just begun its next episode: killed in it
                os.kill(pids[finished.actor], signal.SIGKILL)
                killed.append(pids[finished.actor])
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


def test_without_an_address_a_run_starts_a_ray_of_its_own_beside_a_running_cluster(ray_cluster):
    """`train --actors N` (and `compare`, `bench learning --actors`) without --address: a local
    Ray of N CPUs, not the cluster `ray start` left on this machine."""
    import exit_decision
    from exit_decision.learning.actors import start_ray
    start_ray(None, 1, Path(exit_decision.__file__).resolve().parent.parent)
    import ray   # after start_ray: it sets what Ray reads at import (loopback only)
    try:
        assert ray.cluster_resources().get('CPU') == 1, ray.cluster_resources()
    finally:
        ray.shutdown()


def test_the_comparison_sweep_joins_a_running_cluster(ray_cluster, tmp_path):
    from exit_decision.experiments.compare import Job, SweepResult, run_on_ray

    def where() -> int:   # nested: Ray ships it by value
        import os
        return os.getpid()

    got = []
    result = run_on_ray([Job('where', where, (), got.append)], SweepResult(cells=1), ray_cluster, None, 0, False)
    assert result.done == 1 and got and got[0] != os.getpid(), 'the task ran in a worker of the cluster'


def table_rows(table: str) -> dict[str, list[str]]:
    """``actor_table``'s rows by their number of actors, each as its figures (the '|' dropped)."""
    return {words[0]: [word for word in words if word != '|'] for words in map(str.split, table.splitlines())
            if words and words[0].isdigit()}


def test_the_actor_table_gives_each_count_its_rates_the_cost_of_learning_and_the_scaling_against_its_ceiling():
    from exit_decision.benchmarks import Collected, actor_table

    learning = {0: Collected(1000, 2000, 10.0), 1: Collected(1000, 1000, 8.0, start=5.0),
                2: Collected(1000, 1000, 5.0, start=6.0)}
    collecting = {0: Collected(1000, 0, 2.5), 1: Collected(1000, 0, 2.0), 2: Collected(1000, 0, 1.25)}
    plain = {1: Collected(1000, 0, 1.8), 2: Collected(1000, 0, 1.0)}
    table = actor_table('the recipe', 50, learning, collecting, plain)
    rows = table_rows(table)
    assert rows['0'] == ['0', '0.0', '10.0', '100', '200.0', '400', '4.00x', '-', '-', '-'], \
        'in this process: the cost of learning, nothing to scale'
    assert rows['1'] == ['1', '5.0', '13.0', '125', '125.0', '500', '4.00x', '1.00x', '556', '1.00x'], \
        'wall = start + episodes; a decision with learning takes 4x one without'
    assert rows['2'] == ['2', '6.0', '11.0', '200', '200.0', '800', '4.00x', '1.60x', '1000', '1.80x']
    assert 'scaling from 1 to 2 actors, updates off: 1.60x; the ceiling, two plain processes over one: 1.80x' in table
    without_one = table_rows(actor_table('the recipe', 50, {2: learning[2]}, {2: collecting[2]}, {2: plain[2]}))
    assert without_one['2'][-5:] == ['800', '4.00x', '-', '1000', '-'], 'no ratio without 1 actor to compare with'


def test_bench_learning_with_actors_trains_and_collects_with_each_count_in_one_table(tmp_path, capsys):
    """The tiny form of `exit-decision bench learning --actors 0 --actors 1 --actors 2`."""
    from exit_decision.cli import main
    config_dir = small_config_dir(tmp_path / 'config')
    override = tmp_path / 'warmup.yaml'
    override.write_text('training: {warmup_decisions: 5}\n')   # updates from the first episode on
    assert main(['bench', 'learning', '--config-dir', str(config_dir), '--override', str(override),
                 '--actors', '1', '--actors', '0', '--training-episodes', '1']) == 0
    out = capsys.readouterr().out
    rows = table_rows(out)
    assert list(rows) == ['0', '1'], f'one row per count, in order: {out}'
    assert float(rows['0'][4]) > 0 and float(rows['1'][4]) > 0, 'the learner updated, here and from the actor'
    assert float(rows['1'][1]) > 0 and rows['1'][7] == rows['1'][9] == '1.00x', 'start timed; 1 actor and 1 process'
    assert float(rows['1'][5]) > 0 and float(rows['1'][8]) > 0, 'collected with updates off, by the actor and a process'
    assert all(float(rows[count][6].rstrip('x')) > 0 for count in rows), 'the cost of learning, here and on an actor'
