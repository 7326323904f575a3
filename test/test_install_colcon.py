"""The README's real Jazzy install path: the pip keys `rosdep install --from-paths <repo> <repo>/msg_defs`
resolves from the shipped rosdep source (rosdep.yaml), `colcon build --paths <repo> <repo>/msg_defs --merge-install`
into a scratch workspace, then every node started from that install with nothing of the package
from the project venv: another interpreter prefix (as /usr is on a Jazzy machine), the
workspace's own local_setup.bash, config and policies through the ament index.

colcon and rosdep come from requirements-colcon.txt, installed once with `pip install --target`
beside the venv (colcon would downgrade the venv's setuptools) into build/test_colcon/ (git-ignored). The
workspace is kept there too and rebuilt only when its inputs change (msg_defs: from scratch;
only the Python package: that package alone), so a second run takes seconds, not minutes.
"""
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from exit_decision.ros.stack.launcher import ros_args
from test_packaging import declared_pip_keys

REPO = Path(__file__).resolve().parent.parent
CACHE = REPO / 'build' / 'test_colcon'
WORKSPACE = CACHE / 'ws'
INSTALL = WORKSPACE / 'install'
MSG_INPUTS = ['msg_defs', 'requirements.txt', 'requirements-colcon.txt']
PACKAGE_INPUTS = ['exit_decision', 'config', 'launch', 'resource', 'setup.py', 'setup.cfg', 'package.xml',
                  'policies/*/policy.pt']


def digest(patterns: list[str]) -> str:
    files = sorted(path for pattern in patterns for path in ([REPO / pattern] if '*' not in pattern
                                                               else REPO.glob(pattern)))
    files = sorted(f for path in files for f in ([path] if path.is_file() else path.rglob('*'))
                   if f.is_file() and '__pycache__' not in f.parts)
    h = hashlib.sha256()
    for path in files:
        h.update(path.relative_to(REPO).as_posix().encode() + b'\0' + path.read_bytes())
    return h.hexdigest()[:16]


def jazzy_tools() -> Path:
    """requirements-colcon.txt installed with --target, once per version of that file."""
    target = CACHE / f'tools-{digest(["requirements-colcon.txt"])}'
    if target.is_dir():
        return target
    scratch = target.with_name(target.name + '.partial')
    shutil.rmtree(scratch, ignore_errors=True)
    result = subprocess.run([sys.executable, '-m', 'pip', 'install', '--quiet', '--disable-pip-version-check',
                             '--no-deps', '--target', str(scratch), '-r', str(REPO / 'requirements-colcon.txt')],
                            capture_output=True, text=True, timeout=600, check=False)
    if result.returncode != 0:
        reachable = subprocess.run([sys.executable, '-m', 'pip', 'index', 'versions', 'colcon-core'],
                                   capture_output=True, text=True, timeout=120, check=False).returncode == 0
        if not reachable:
            pytest.skip('PyPI is unreachable: colcon and rosdep (requirements-colcon.txt) cannot be installed')
        pytest.fail(f'installing requirements-colcon.txt failed:\n{result.stderr[-3000:]}')
    scratch.rename(target)
    return target


def colcon_build(tools: Path, *selection: str) -> None:
    env = {**os.environ, 'PYTHONPATH': str(tools), 'AMENT_PREFIX_PATH': sys.prefix, 'CMAKE_PREFIX_PATH': sys.prefix,
           'PATH': f'{Path(sys.executable).parent}:{os.environ["PATH"]}', 'COLCON_HOME': str(CACHE / 'colcon_home')}
    command = [sys.executable, '-m', 'colcon', 'build', '--paths', str(REPO), str(REPO / 'msg_defs'),
               '--merge-install', *selection, '--event-handlers', 'console_direct-',
               '--cmake-args', f'-DPython3_EXECUTABLE={sys.executable}', '-DBUILD_TESTING=OFF']
    result = subprocess.run(command, cwd=WORKSPACE, env=env, capture_output=True, text=True, timeout=900, check=False)
    assert result.returncode == 0, f'colcon build failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}'


def test_rosdep_resolves_every_pip_key_of_package_xml_from_the_shipped_source(tmp_path):
    """What `rosdep install` would install for the pip keys, asked of rosdep itself (`rosdep
    update`, `rosdep resolve`) with only rosdep.yaml registered (ros/rosdistro, which defines the
    ROS and apt keys, cannot be reached here): each python3-<name>-pip key package.xml declares
    resolves to pip's <name> on Jazzy's platforms (test_packaging.py: <name> is pinned)."""
    tools = jazzy_tools()
    pip_keys = declared_pip_keys()
    sources = tmp_path / 'sources.list.d'
    sources.mkdir()
    (sources / '10-exit-decision.list').write_text(f'yaml {(REPO / "rosdep.yaml").as_uri()}\n')
    index = tmp_path / 'index.yaml'
    index.write_text('%YAML 1.1\n---\ndistributions: {}\ntype: index\nversion: 4\n')
    env = {'PATH': os.environ['PATH'], 'PYTHONPATH': str(tools), 'ROSDEP_SOURCE_PATH': str(sources),
           'ROS_HOME': str(tmp_path / 'ros_home'), 'ROSDISTRO_INDEX_URL': index.as_uri(), 'ROS_PYTHON_VERSION': '3'}

    def rosdep(*args: str) -> str:
        result = subprocess.run([sys.executable, '-m', 'rosdep2', *args], env=env, capture_output=True, text=True,
                                timeout=120, check=False)
        assert result.returncode == 0, f'rosdep {" ".join(args)}:\n{result.stdout}{result.stderr}'
        return result.stdout

    rosdep('update')
    for platform in ('ubuntu:noble', 'debian:bookworm', 'rhel:9'):
        resolved = dict(re.findall(r'#ROSDEP\[(.+?)\]\n#pip\n(.+)\n', rosdep('resolve', *sorted(pip_keys),
                                                                              f'--os={platform}')))
        assert resolved == pip_keys, platform


@pytest.fixture(scope='module')
def install() -> Path:
    """The scratch workspace's install/, built or brought up to date."""
    tools = jazzy_tools()
    msgs, package = digest(MSG_INPUTS), digest(PACKAGE_INPUTS)
    stamps = {name: WORKSPACE / f'.inputs_{name}' for name in ('msgs', 'package')}
    if not stamps['msgs'].is_file() or stamps['msgs'].read_text() != msgs:
        shutil.rmtree(WORKSPACE, ignore_errors=True)
        WORKSPACE.mkdir(parents=True)
        colcon_build(tools)
        stamps['msgs'].write_text(msgs)
    elif not stamps['package'].is_file() or stamps['package'].read_text() != package:
        colcon_build(tools, '--packages-select', 'exit_decision')
    stamps['package'].write_text(package)
    return INSTALL


@pytest.fixture(scope='module')
def bare_python() -> Path:
    """An interpreter whose prefix holds nothing of the package (like /usr/bin/python3 on a Jazzy
    machine); the venv's libraries are importable after anything PYTHONPATH names."""
    root = CACHE / 'python'
    python = root / 'bin' / 'python'
    if not python.exists():
        subprocess.run([sys._base_executable, '-m', 'venv', '--without-pip', str(root)], check=True, timeout=120)
        site = next((root / 'lib').glob('python3*/site-packages'))
        venv_site = next(Path(sys.prefix, 'lib').glob('python3*/site-packages'))
        (site / 'project_venv_libraries.pth').write_text(f'{venv_site}\n')
    return python


@pytest.fixture(scope='module')
def environment(install) -> dict[str, str]:
    """What a user has after sourcing the underlay (the venv's ROS wheels) and then the
    workspace's install/local_setup.bash."""
    base = {key: value for key, value in os.environ.items() if key not in ('PYTHONPATH', 'CMAKE_PREFIX_PATH')}
    base['AMENT_PREFIX_PATH'] = sys.prefix
    result = subprocess.run(['bash', '-c', f'source {install}/local_setup.bash && env -0'], env=base,
                            capture_output=True, timeout=60, check=True)
    return dict(item.split('=', 1) for item in result.stdout.decode().split('\0') if '=' in item)


def test_the_package_config_and_policies_come_from_the_install(install, bare_python, environment):
    code = ('import sys, exit_decision, exit_decision_msgs\n'
            'from exit_decision.config import default_config_dir, default_rviz_config\n'
            'from exit_decision.model.names import default_policy_dir\n'
            'print(exit_decision.__file__, exit_decision_msgs.__file__, default_config_dir(), default_policy_dir(),\n'
            '      default_rviz_config())\n'
            'print(sys.prefix)')
    result = subprocess.run([str(bare_python), '-c', code], env=environment, capture_output=True, text=True,
                            timeout=120, cwd=install.parent, check=False)
    assert result.returncode == 0, result.stderr
    paths, prefix = result.stdout.split('\n')[:2]
    for path in paths.split():
        assert Path(path).is_relative_to(install), f'{path} is not from {install}'
    assert Path(paths.split()[-1]).is_file(), 'the launch file\'s rviz:=true view is installed'
    assert not (Path(prefix) / 'share' / 'exit_decision').exists()


@pytest.mark.parametrize('deciding', [('graph_builder', 'decision_node'), ('graph_and_decision',)],
                         ids=['alone', 'composed'])
def test_every_node_starts_from_the_install(install, bare_python, environment, tmp_path, deciding):
    """``deciding``: the graph builder and the decision node as two processes, or composed in one."""
    from diagnostic_msgs.msg import DiagnosticArray
    from exit_decision_msgs.msg import CavCommandArray, TrafficGraph, VehicleStateArray
    from rosbags.rosbag2 import Reader
    from visualization_msgs.msg import MarkerArray

    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.topics import (COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, GRAPH_TOPIC, MARKERS_TOPIC, STATES_TOPIC,
                                          STREAM_QOS)

    def start(name: str, parameters: dict) -> subprocess.Popen:
        return subprocess.Popen([str(bare_python), str(install / 'lib' / 'exit_decision' / name),
                                 *ros_args(parameters)], env=environment, cwd=tmp_path,
                                stdout=open(tmp_path / f'{name}.log', 'w'), stderr=subprocess.STDOUT,
                                start_new_session=True)

    def log(name: str) -> str:
        return (tmp_path / f'{name}.log').read_text()

    seen: dict[str, int] = {}
    probe = ProbeNode('colcon_probe')
    for msg_type, topic in ((VehicleStateArray, STATES_TOPIC), (TrafficGraph, GRAPH_TOPIC),
                            (CavCommandArray, COMMANDS_TOPIC), (MarkerArray, MARKERS_TOPIC),
                            (DiagnosticArray, DIAGNOSTICS_TOPIC)):
        probe.node.create_subscription(msg_type, topic, lambda _, t=topic: seen.__setitem__(t, seen.get(t, 0) + 1),
                                       STREAM_QOS)
    bag = tmp_path / 'bag'
    processes = {name: start(name, parameters) for name, parameters in (
        ('recorder', {'bag_path': str(bag)}), *[(name, {}) for name in deciding], ('visualizer', {}))}
    listeners = len(processes) + 1   # each process listens to the states once (composed too), and the probe
    try:
        # each started alone keeps waiting for its peers, listening to the states
        assert probe.spin_until(lambda: probe.node.count_subscribers(STATES_TOPIC) >= listeners, 120), \
            {name: log(name)[-1000:] for name in processes}
        processes['sumo_bridge'] = start('sumo_bridge', {'episodes': 1, 'wait_for_subscribers': listeners})
        # 3 commands answer decision steps 0, 5 and 10: the states and graphs of 11 steps came before
        # them (each topic's messages may arrive at the probe in any order relative to the others)
        enough = lambda: (seen.get(COMMANDS_TOPIC, 0) >= 3 and seen.get(MARKERS_TOPIC, 0) >= 1  # noqa: E731
                          and seen.get(GRAPH_TOPIC, 0) >= 3 and seen.get(STATES_TOPIC, 0) >= 11)
        probe.spin_until(lambda: any(p.poll() is not None for p in processes.values()) or enough(), 180)
        dead = {name: log(name)[-1500:] for name, p in processes.items() if p.poll() is not None}
        assert not dead, dead
        assert enough(), seen
        assert f'from {install}/share/exit_decision/policies' in log(deciding[-1])
    finally:
        for name in ['sumo_bridge', *deciding, 'visualizer', 'recorder']:
            if name in processes and processes[name].poll() is None:
                processes[name].send_signal(signal.SIGINT)
        for process in processes.values():
            try:
                process.wait(20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    assert processes['recorder'].returncode == 0, log('recorder')[-2000:]
    # the player republishes that bag to the probe, then ends
    seen.clear()
    player = start('player', {'bag_path': str(bag), 'wait_for_subscribers': 1, 'rate': 10.0})
    try:
        assert probe.spin_until(lambda: player.poll() is not None, 180), log('player')[-2000:]
        probe.spin_until(lambda: False, 1.0)
    finally:
        if player.poll() is None:
            player.kill()
            player.wait()
        probe.close()
    assert player.returncode == 0, log('player')[-2000:]
    with Reader(bag) as reader:   # what the recorder had when it was stopped: every state of it comes back
        recorded = sum(c.msgcount for c in reader.connections if c.topic == STATES_TOPIC)
    assert recorded >= 1 and seen.get(STATES_TOPIC, 0) >= recorded, (recorded, log('player')[-2000:])
