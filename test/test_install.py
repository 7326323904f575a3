"""The ament layout of the installed package (what `ros2 run` and ros2cli look up) and the CLI."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

PREFIX = Path(sys.prefix)
REPO = Path(__file__).resolve().parent.parent


def test_ament_index_and_share_and_executables():
    assert (PREFIX / 'share/ament_index/resource_index/packages/exit_decision').is_file()
    assert (PREFIX / 'share/ament_index/resource_index/packages/exit_decision_msgs').is_file()
    assert (PREFIX / 'share/exit_decision/package.xml').is_file()
    for name in ('scenario', 'graph', 'env', 'modes', 'reward'):
        assert (PREFIX / f'share/exit_decision/config/{name}.yaml').is_file()
    executable = PREFIX / 'lib/exit_decision/exit-decision'
    assert os.access(executable, os.X_OK)


def test_ament_prefix_defaults_to_the_venv():
    from ament_index_python.packages import get_package_share_directory
    assert Path(get_package_share_directory('exit_decision')) == PREFIX / 'share/exit_decision'


def cli(*args, **kwargs):
    return subprocess.run([sys.executable, '-m', 'exit_decision', *args], cwd=REPO, capture_output=True,
                          text=True, timeout=300, **kwargs)


@pytest.mark.parametrize('command', ['run', 'stack', 'train', 'evaluate', 'ablation', 'plot', 'report', 'replay', 'bench'])
def test_every_command_has_help(command):
    result = cli(command, '--help')
    assert result.returncode == 0 and 'usage: exit-decision' in result.stdout


def test_run_prints_the_metrics_table():
    result = cli('run', '--episodes', '1', '--seed', '0')
    assert result.returncode == 0, result.stderr
    header = next(line for line in result.stdout.splitlines() if line.startswith('| run'))
    for metric in ('v_AVs', 'v_s', 'p_collision', 'p_collision_CAV', 'N_braking', 'p_CAV', 'p_HV2', 'reward'):
        assert f' {metric} ' in header


def test_invalid_config_fails_with_the_key_and_exit_code_2(tmp_path):
    override = tmp_path / 'bad.yaml'
    override.write_text('road: {lane_count: 0}\n')
    result = cli('run', '--scenario-override', str(override))
    assert result.returncode == 2
    assert 'road.lane_count' in result.stderr
    assert 'Traceback' not in result.stderr


def test_unknown_mode_is_refused_with_the_known_ones():
    result = cli('run', '--score-mode', 'FAST')
    assert result.returncode == 2
    assert "unknown mode 'FAST'" in result.stderr and 'AGGI' in result.stderr
