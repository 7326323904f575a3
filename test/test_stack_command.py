"""`exit-decision stack` ends cleanly however it is ended: SIGINT (Ctrl-C) and SIGTERM stop every
node it started and leave a finished bag; a node that exits at start stops the others and the
command says why in one line. The nodes run in sessions of their own, so nothing but the
launcher can stop them: a node left running would be found by its command line."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from exit_decision.ros.bags.storage import read_messages
from exit_decision.ros.topics import STATES_TOPIC

from ros_helpers import random_policies, small_config_dir


@pytest.fixture(scope='module')
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp('stack_command')
    config_dir = small_config_dir(root / 'config')
    return {'config_dir': config_dir, 'policies': random_policies(config_dir, root / 'policies')}


def processes_naming(text: str) -> list[int]:
    """Pids of the processes whose command line holds ``text`` (the nodes get the run's config_dir)."""
    found = []
    for entry in Path('/proc').iterdir():
        if entry.name.isdigit():
            try:
                if text.encode() in (entry / 'cmdline').read_bytes():
                    found.append(int(entry.name))
            except OSError:   # ended meanwhile
                pass
    return found


def stack(tmp_path: Path, config_dir: Path, *args: str) -> subprocess.Popen:
    """`exit-decision stack` on the test's config and policies, in tmp_path (its logs there)."""
    return subprocess.Popen([sys.executable, '-m', 'exit_decision', 'stack', '--config-dir', str(config_dir), *args],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def finish(process: subprocess.Popen, timeout: float) -> tuple[str, str]:
    try:
        return process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        raise


def kill_left(config_dir: Path) -> list[int]:
    left = processes_naming(str(config_dir))
    for pid in left:   # not to leave them to later tests
        os.kill(pid, signal.SIGKILL)
    return left


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_every_node_and_finishes_the_bag(setup, tmp_path, sig):
    config_dir = tmp_path / 'config'   # a path of its own: it names this run's nodes
    config_dir.symlink_to(setup['config_dir'], target_is_directory=True)
    bag = tmp_path / 'bag'
    process = stack(tmp_path, config_dir, '--episodes', '0', '--policy',
                    str(setup['policies'] / 'mdgqn_options_conditioned'), '--bag', str(bag))
    try:
        deadline = time.monotonic() + 180
        # every node is up (recorder, graph_and_decision, visualizer, bridge) and states are recorded
        while not (len(set(processes_naming(str(config_dir))) - {process.pid}) == 4 and (bag / 'bag.mcap').is_file()
                   and (bag / 'bag.mcap').stat().st_size > 50_000):
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, 'the stack did not get going within 180 s'
            time.sleep(0.2)
        process.send_signal(sig)
        out, err = finish(process, 60)
    finally:
        left = kill_left(config_dir)
    assert not left, f'nodes left running after {sig.name}: {left}'
    assert process.returncode == 0 and 'Traceback' not in err, (process.returncode, err)
    assert f'stopped by {sig.name}' in out and f'bag: {bag}' in out, out
    assert (bag / 'metadata.yaml').is_file(), 'the recorder closed the bag'
    states = [msg for _, _, _, msg in read_messages(bag, {STATES_TOPIC})]
    assert len(states) > 50, 'the bag holds what was recorded until the signal'


def test_a_node_that_cannot_start_stops_the_others_and_the_command_says_why_in_one_line(setup, tmp_path):
    config_dir = tmp_path / 'config'
    config_dir.symlink_to(setup['config_dir'], target_is_directory=True)
    empty = tmp_path / 'no_policies'
    (empty / 'mdgqn_options_conditioned').mkdir(parents=True)
    (empty / 'mdgqn_options_conditioned' / 'policy.pt').write_text('not a checkpoint')   # found, but cannot load
    bag = tmp_path / 'bag'
    process = stack(tmp_path, config_dir, '--policy', str(empty / 'mdgqn_options_conditioned'), '--bag', str(bag))
    try:
        out, err = finish(process, 180)
    finally:
        left = kill_left(config_dir)
    assert not left, f'nodes left running: {left}'
    lines = err.strip().splitlines()
    assert process.returncode == 1 and len(lines) == 1, err
    assert lines[0].startswith('exit-decision: stack: graph_and_decision exited with code 1: '
                               '[graph_and_decision] cannot start: ') and str(empty) in lines[0], lines[0]
    assert (bag / 'metadata.yaml').is_file(), 'the recorder, stopped, closed its bag'
