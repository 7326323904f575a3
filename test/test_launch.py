"""The one node table behind the launch file and `exit-decision stack`, use_sim_time, and the
loopback default every process of the project starts with."""
import importlib.util
import os
import re
import signal
import subprocess
import sys
import threading
import types
from pathlib import Path

import pytest

from exit_decision.ros.stack.node_table import ARGUMENTS, BRIDGE, NODE_NAMES, NODES, plan, process_of

REPO = Path(__file__).resolve().parent.parent
LAUNCH_FILE = REPO / 'launch' / 'exit_decision.launch.py'


class Recorded:
    """Stands in for a `launch` / `launch_ros` class (not installable here): keeps its arguments."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def launch_description(monkeypatch, given: dict[str, str]):
    """The launch file's actions, its nodes resolved for ``given`` (launch-style text values)."""
    names = {'launch': ['LaunchDescription'], 'launch.actions': ['DeclareLaunchArgument', 'OpaqueFunction', 'Shutdown'],
             'launch_ros': [], 'launch_ros.actions': ['Node']}
    for module, classes in names.items():
        stub = types.ModuleType(module)
        for name in classes:
            setattr(stub, name, type(name, (Recorded,), {}))
        monkeypatch.setitem(sys.modules, module, stub)

    class LaunchConfiguration:
        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return context.get(self.name, ARGUMENTS[self.name].default)

    substitutions = types.ModuleType('launch.substitutions')
    substitutions.LaunchConfiguration = LaunchConfiguration
    monkeypatch.setitem(sys.modules, 'launch.substitutions', substitutions)
    spec = importlib.util.spec_from_file_location('exit_decision_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    actions = module.generate_launch_description().args[0]
    declared = {a.args[0]: a.kwargs['default_value'] for a in actions if type(a).__name__ == 'DeclareLaunchArgument'}
    opaque = [a for a in actions if type(a).__name__ == 'OpaqueFunction']
    return declared, opaque[0].kwargs['function'](given)


@pytest.mark.parametrize('given', [{}, {'visualizer': 'false', 'config_dir': '/tmp/c', 'episodes': '3'}])
def test_launch_file_starts_the_tables_nodes_and_shuts_down_when_any_of_them_ends(monkeypatch, given):
    """The bridge's exit ends the launch (its episodes are run), and so does any other node's: one
    that cannot start (its one line says why) never leaves the bridge waiting for it."""
    declared, actions = launch_description(monkeypatch, given)
    assert declared == {name: argument.default for name, argument in ARGUMENTS.items()}
    nodes = [a for a in actions if type(a).__name__ == 'Node']
    assert [(n.kwargs['executable'], n.kwargs['parameters'][0]) for n in nodes] == plan(given)
    # a single node is named as its executable; a composed process is not named (a name would rename its nodes)
    assert all(n.kwargs['package'] == 'exit_decision' for n in nodes)
    assert {n.kwargs['executable']: n.kwargs['name'] for n in nodes} == {
        executable: executable if names == (executable,) else None for executable, names in NODE_NAMES.items()
        if executable in dict(plan(given))}
    assert len(actions) == len(nodes), 'nothing but the nodes'
    for node in nodes:
        (shutdown,) = node.kwargs['on_exit']
        assert type(shutdown).__name__ == 'Shutdown', node.kwargs
        reason = shutdown.kwargs['reason']
        assert reason == (f'{BRIDGE} has run its episodes' if node.kwargs['executable'] == BRIDGE else
                          f'{node.kwargs["executable"]} exited; the stack cannot go on without it')


def test_the_launch_file_starts_as_the_stack_command_does_and_a_second_run_gets_a_new_bag(monkeypatch):
    """One start mode: the mode `exit-decision stack` starts in (the matrix's aggressive punished
    mode); no bag path given: the recorder's time-stamped default, so a second launch works; the
    recorder's compression by default (`exit-decision stack` takes this argument's default too)."""
    from exit_decision.config import load_project
    from exit_decision.ros.bags import storage
    from exit_decision.ros.nodes import recorder

    declared, actions = launch_description(monkeypatch, {})
    assert declared['mode'] == load_project().mode_matrix.aggressive.punished == 'AGGP'
    nodes = {a.kwargs['executable']: a.kwargs['parameters'][0] for a in actions}
    assert nodes['graph_and_decision']['mode'] == 'AGGP'
    assert declared['bag_path'] == '' and 'bag_path' not in nodes['recorder']
    assert declared['compression'] == nodes['recorder']['compression'] == recorder.DEFAULT_COMPRESSION == 'zstd'
    assert sorted(ARGUMENTS['compression'].choices) == sorted(storage.COMPRESSIONS)
    refusal = "argument compression: 'gzip' is not allowed; allowed: zstd | none"
    with pytest.raises(ValueError, match=re.escape(refusal)):
        plan({'compression': 'gzip'})


def test_rviz_true_also_starts_rviz2_with_the_shipped_view_and_its_exit_ends_nothing(monkeypatch):
    """rviz:=true: the table's nodes as without it, and rviz2 on the shipped config of the markers
    (rviz/exit_decision.rviz, installed to share/exit_decision/rviz by setup.py); off by default."""
    from exit_decision.config import default_rviz_config

    assert ARGUMENTS['rviz'].default == 'false'
    _, without = launch_description(monkeypatch, {})
    assert all(a.kwargs['package'] == 'exit_decision' for a in without)
    _, actions = launch_description(monkeypatch, {'rviz': 'true'})
    (viewer,) = [a for a in actions if a.kwargs['package'] == 'rviz2']
    assert [(a.kwargs['executable'], a.kwargs['parameters'][0]) for a in actions if a is not viewer] == plan({})
    config = Path(viewer.kwargs['arguments'][1])
    assert viewer.kwargs['arguments'][0] == '-d' and config == default_rviz_config() and config.is_file()
    assert 'on_exit' not in viewer.kwargs, 'closing RViz leaves the stack running'
    text = config.read_text()
    assert 'Fixed Frame: map' in text and 'Value: /exit_decision/markers' in text
    assert "glob('rviz/*.rviz')" in (REPO / 'setup.py').read_text(), 'installed beside config/'


def test_the_bridge_waits_for_every_state_listener_of_the_plan():
    full, without = plan({}), plan({'visualizer': False})
    assert [name for name, _ in full] == [node.executable for node in NODES] and full[-1][0] == BRIDGE
    assert 'visualizer' not in dict(without)
    # recorder, visualizer, and the graph builder of graph_and_decision (its decision node takes its graphs in the process)
    assert dict(full)[BRIDGE]['wait_for_subscribers'] == 3
    assert dict(without)[BRIDGE]['wait_for_subscribers'] == 2
    assert dict(plan({}, extra_listeners=1))[BRIDGE]['wait_for_subscribers'] == 4
    assert process_of('decision_node', dict(full)) == process_of('graph_builder', dict(full)) == 'graph_and_decision'


def test_arguments_become_typed_parameters_and_empty_ones_keep_the_nodes_default():
    nodes = dict(plan({'episodes': '2', 'use_sim_time': 'true', 'policy_dir': ''}))
    assert nodes[BRIDGE]['episodes'] == 2 and nodes[BRIDGE]['use_sim_time'] is True
    assert all(node['use_sim_time'] is True for node in nodes.values())
    assert 'policy_dir' not in nodes['graph_and_decision'] and 'config_dir' not in nodes['graph_and_decision']
    with pytest.raises(ValueError, match="argument visualizer: 'yes' is not allowed; allowed: true or false"):
        plan({'visualizer': 'yes'})
    with pytest.raises(ValueError, match='unknown argument'):
        plan({'speed': '3'})


@pytest.mark.parametrize('usable, expected', [
    ([0, 1], ([0], [1])), ([4, 5, 6], ([4, 5], [6])), ([0, 1, 2, 3], ([0, 1], [2, 3])), ([3], None)])
def test_the_decision_path_and_the_onlookers_get_cores_of_their_own(monkeypatch, usable, expected):
    """cpu_split (the default): the bridge and graph_and_decision on the first half of the cores
    the stack may use, the recorder and the visualizer on the rest; no pinning when false, with
    a real-time thread_priority, or with one core."""
    from exit_decision.ros.stack import cpu_affinity
    monkeypatch.setattr(cpu_affinity, 'usable', lambda: usable)
    nodes = dict(plan({}))
    if expected is None:
        assert not any('cpu_affinity' in parameters for parameters in nodes.values()), nodes
        return
    path, onlookers = expected
    assert {name: parameters['cpu_affinity'] for name, parameters in nodes.items()} == {
        'recorder': onlookers, 'graph_and_decision': path, 'visualizer': onlookers, BRIDGE: path}
    for off in ({'cpu_split': 'false'}, {'thread_priority': '10'}):
        assert not any('cpu_affinity' in parameters for parameters in dict(plan(off)).values()), off


def test_every_node_of_the_table_is_a_console_script():
    import ast
    tree = ast.parse((REPO / 'setup.py').read_text())
    scripts = next(node for node in ast.walk(tree) if isinstance(node, ast.Dict)
                   and any(isinstance(k, ast.Constant) and k.value == 'console_scripts' for k in node.keys))
    entries = [item.value.split('=')[0].strip() for item in scripts.values[0].elts]
    # the two composed nodes can also run alone (ros2 run exit_decision decision_node)
    assert {node.executable for node in NODES} | {'player', 'graph_builder', 'decision_node'} <= set(entries)


# --- loopback default ------------------------------------------------------------------------

def python(code: str, **env_changes) -> str:
    env = {key: value for key, value in os.environ.items() if key != 'ROS_AUTOMATIC_DISCOVERY_RANGE'}
    env.update(env_changes)
    env = {key: value for key, value in env.items() if value is not None}   # None: unset
    result = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True, timeout=120,
                            cwd=REPO, check=False)
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


LAUNCHER_CHILD = '''
import os, time
from pathlib import Path
from exit_decision.ros.stack.launcher import start_node
from exit_decision.ros.probe import ProbeNode
probe = ProbeNode('loopback_probe')   # the launcher's helper node: created in this same process
child = start_node('graph_builder', {}, Path(os.devnull))
environ = b''
while b'ROS_AUTOMATIC_DISCOVERY_RANGE' not in environ and child.poll() is None:
    time.sleep(0.05)
    environ = Path(f'/proc/{child.pid}/environ').read_bytes()
child.kill(); child.wait(); probe.close()
own = os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']
theirs = dict(v.split(b'=', 1) for v in environ.split(b'\\0') if b'=' in v)[b'ROS_AUTOMATIC_DISCOVERY_RANGE'].decode()
print(own, theirs)
'''


def test_the_launcher_its_helper_node_and_its_nodes_keep_dds_on_loopback_by_default():
    assert python(LAUNCHER_CHILD) == 'LOCALHOST LOCALHOST'


def test_a_users_explicit_discovery_range_wins():
    # OFF: no discovery at all, so this test never reaches beyond the machine either
    assert python(LAUNCHER_CHILD, ROS_AUTOMATIC_DISCOVERY_RANGE='OFF') == 'OFF OFF'


LAUNCH_PROCESS = f'''
import importlib.util, os, sys, types
for module, names in {{'launch': ['LaunchDescription'], 'launch.actions': ['DeclareLaunchArgument',
        'OpaqueFunction', 'Shutdown'], 'launch.substitutions': ['LaunchConfiguration'],
        'launch_ros': [], 'launch_ros.actions': ['Node']}}.items():
    stub = sys.modules[module] = types.ModuleType(module)
    for name in names:
        setattr(stub, name, type(name, (), {{}}))
spec = importlib.util.spec_from_file_location('launch_file', {str(LAUNCH_FILE)!r})
spec.loader.exec_module(importlib.util.module_from_spec(spec))
print(os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'], 'rclpy' in sys.modules, os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'],
      os.environ.get('RMW_FASTRTPS_USE_QOS_FROM_XML'))
'''


def test_the_ros2_launch_process_keeps_dds_on_loopback_before_any_node_and_a_users_choice_wins():
    """The launch file sets the defaults in the `ros2 launch` process itself (launch_ros may
    start a node there; every node it starts inherits them), without importing rclpy."""
    loopback, rclpy_loaded, profile, from_xml = python(LAUNCH_PROCESS, FASTRTPS_DEFAULT_PROFILES_FILE=None,
                                                       RMW_FASTRTPS_USE_QOS_FROM_XML=None).split(' ')
    assert (loopback, rclpy_loaded, from_xml) == ('LOCALHOST', 'False', '1') and profile.endswith('config/fastdds.xml')
    assert python(LAUNCH_PROCESS, ROS_AUTOMATIC_DISCOVERY_RANGE='OFF', FASTRTPS_DEFAULT_PROFILES_FILE='mine.xml',
                  RMW_FASTRTPS_USE_QOS_FROM_XML=None) == 'OFF False mine.xml None'


def test_every_entry_point_takes_the_default_from_one_place():
    """Every console script imports ``executor`` (``run_node``; importing it sets the default),
    the launcher imports ``probe`` (its helper node), which imports ``executor``, and these two
    are the only modules that start rclpy."""
    import ast
    starters = set()
    for path in (REPO / 'exit_decision').rglob('*.py'):
        if 'rclpy.init(' in path.read_text():
            starters.add(path.relative_to(REPO).as_posix())
    assert starters == {'exit_decision/ros/executor.py', 'exit_decision/ros/probe.py'}
    executables = [f'nodes/{node.executable}' for node in NODES] + ['nodes/graph_builder', 'nodes/decision_node',
                                                                   'nodes/player']
    expected = ([(module, 'exit_decision.ros.executor') for module in executables]
                + [('stack/launcher', 'exit_decision.ros.probe'), ('probe', 'exit_decision.ros.executor')])
    for module, sets_default in expected:
        tree = ast.parse((REPO / 'exit_decision' / 'ros' / f'{module}.py').read_text())
        imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
        assert sets_default in imported, module
    for module in ('executor', 'probe'):
        code = f'import os, exit_decision.ros.{module}; print(os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"])'
        assert python(code) == 'LOCALHOST'


# --- use_sim_time --------------------------------------------------------------------------------

def test_sigterm_stops_a_decision_node_on_sim_time_with_no_clock(tmp_path):
    from rcl_interfaces.srv import GetParameters

    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.stack.launcher import start_node

    process = start_node('decision_node', {'use_sim_time': True, 'modes': ['AGGI'],
                                           'algorithms': ['mdgqn_conditioned']}, tmp_path / 'decision.log')
    probe = ProbeNode('sim_time_probe')
    try:
        client = probe.node.create_client(GetParameters, '/decision_node/get_parameters')
        assert probe.spin_until(client.service_is_ready, 60), 'decision_node did not come up'
        response = probe.call(client, GetParameters.Request(names=['use_sim_time']), timeout=60)   # once it spins
        assert response is not None and response.values[0].bool_value
        process.send_signal(signal.SIGTERM)
        process.wait(30)
    finally:
        probe.close()
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 0, (tmp_path / 'decision.log').read_text()[-2000:]


def test_every_node_runs_on_the_bridges_clock(tmp_path):
    """The stack with use_sim_time: an episode ends, and every node stamps its diagnostics with
    simulation time (seconds since the episode's start, not since 1970)."""
    from diagnostic_msgs.msg import DiagnosticArray

    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.topics import DIAGNOSTICS_TOPIC, STREAM_QOS
    from exit_decision.ros.stack.launcher import run_stack

    from ros_helpers import random_policies, small_config_dir

    config_dir = small_config_dir(tmp_path / 'config')
    policies = random_policies(config_dir, tmp_path / 'policies')
    stamps: dict[str, list[float]] = {}
    probe = ProbeNode('clock_probe')
    probe.node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, lambda msg: [
        stamps.setdefault(s.name, []).append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
        for s in msg.status], STREAM_QOS)
    done = threading.Event()
    spinner = threading.Thread(target=lambda: probe.spin_until(done.is_set, 600))
    spinner.start()
    try:
        run = run_stack(mode='AGGI', algorithm='mdgqn_conditioned', episodes=2, seed=10_000,
                        bag_path=tmp_path / 'bag', log_dir=tmp_path / 'logs', config_dir=str(config_dir),
                        policy_dir=str(policies), timeout=300, use_sim_time=True)
    finally:
        done.set()
        spinner.join()
        probe.close()
    assert len(run.episodes) == 2
    assert sorted(run.return_codes) == sorted(name for name, _ in plan({}))
    episode_time = sum(e['steps'] for e in run.episodes) * 0.1 + 1.0
    for name in ('sumo_bridge', 'graph_builder', 'decision_node', 'recorder', 'visualizer'):
        assert name in stamps, f'no diagnostics from {name}'
        assert max(stamps[name]) < episode_time, f'{name} is not on the simulation clock: {stamps[name][-3:]}'
    assert max(max(values) for values in stamps.values()) > 0, 'the clock advanced'


def test_one_shipped_policy_starts_everywhere_the_node_the_launch_file_and_the_stack_command():
    """`ros2 run exit_decision decision_node` (and graph_and_decision), the launch file and
    `exit-decision stack` all start on the shipped policy, one constant."""
    from exit_decision.cli import build_parser
    from exit_decision.cli.stack import stack_policy
    from exit_decision.model.names import DEFAULT_ALGORITHM, SHIPPED_ALGORITHMS
    from exit_decision.ros.parameters import start_algorithm

    stack = build_parser().parse_args(['stack'])
    assert start_algorithm(list(SHIPPED_ALGORITHMS)) == ARGUMENTS['algorithm'].default \
        == stack_policy(stack.policy, None)[1] == DEFAULT_ALGORITHM
    assert start_algorithm(['gqn']) == 'gqn', 'another set of algorithms: the last loaded'
