"""Start the whole stack as separate processes on a machine without `ros2 launch`.

The nodes of the one table (``node_table.plan``, which the launch file starts too), each the
executable `ros2 run exit_decision <exe>` starts (lib/exit_decision/<exe>), with parameters as
`--ros-args -p`; the bridge once the others are listening. Optionally switches the decision
mode once mid-run through the decision node's standard set_parameters service (what `ros2
param set` calls). When the bridge has run its episodes, the others get SIGINT (SIGKILL if
they hang), and the episode metrics (from the episode events) and the bag path are returned.
Every process inherits the loopback default that importing ``probe`` (through ``executor``) sets.

The nodes run in sessions of their own (a Ctrl-C in the terminal reaches only the launcher),
so the launcher stops them whatever ends the run: the bridge's last episode; SIGINT (Ctrl-C)
or SIGTERM to the launcher (the run ends early, the bag is finished: ``StackRun.stopped_by``);
or a node that exits before the run ends (it could not start, or died): then ``StackError``
names the node, its exit code and its log's last line (a node that cannot start says why in
one line).
"""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from exit_decision_msgs.msg import CavCommandArray, EpisodeEvent, VehicleStateArray
from rcl_interfaces.srv import SetParameters

from exit_decision.ros.probe import ProbeNode
from exit_decision.ros.topics import COMMANDS_TOPIC, EPISODE_TOPIC, EVENT_QOS, MARKERS_TOPIC, STATES_TOPIC, STREAM_QOS
from exit_decision.ros.messages.conversions import metrics_from_event
from exit_decision.ros.stack.cpu_affinity import pinned
from exit_decision.ros.stack.node_table import BRIDGE, cores, plan
from exit_decision.errors import StackError
from exit_decision.input_checks import InputError
from exit_decision.step_gaps import episode_and_step


def executable(name: str) -> list[str]:
    """The installed ament executable, or the module when running from a checkout only."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    try:
        installed = Path(get_package_prefix('exit_decision')) / 'lib' / 'exit_decision' / name
    except PackageNotFoundError:
        installed = None
    if installed is not None and installed.is_file() and os.access(installed, os.X_OK):
        return [str(installed)]
    return [sys.executable, '-m', f'exit_decision.ros.nodes.{name}']


def ros_args(parameters: dict[str, object]) -> list[str]:
    args = ['--ros-args']
    for key, value in parameters.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        args += ['-p', f'{key}:={text}']
    return args


def start_node(name: str, parameters: dict[str, object], log: Path) -> subprocess.Popen:
    """One node as its own process (own session, so a Ctrl-C in a terminal reaches only us),
    output to ``log``."""
    return subprocess.Popen(executable(name) + ros_args(parameters), stdout=open(log, 'w'),
                            stderr=subprocess.STDOUT, start_new_session=True)


@dataclass
class SwitchSteps:
    """Where one mode switch happened, in steps of the first episode: the launcher asks for it
    at the first state it sees at or past the step asked for, and the decision node's next
    decision (every decision_interval steps) after the service's answer is the first in the
    new mode."""
    asked: int                     # --switch-at
    requested: int = -1            # the step of the state the launcher had seen when it called the service
    answered: int = -1             # the step it had seen when the answer came
    landed: int = -1               # the first command in the new mode (-1: none seen)


@dataclass
class StackRun:
    bag_path: Path
    episodes: list[dict[str, float]] = field(default_factory=list)
    mode_switch: str = ''          # what the set_parameters call answered
    switch: SwitchSteps | None = None
    return_codes: dict[str, int] = field(default_factory=dict)
    stopped_by: str = ''           # SIGINT or SIGTERM: the launcher was stopped before the run ended


def last_line(log: Path) -> str:
    """The last non-empty line of a node's log (a node that cannot start says why in it)."""
    try:
        lines = log.read_text(errors='replace').strip().splitlines()
    except OSError:
        return ''
    return lines[-1].strip() if lines else ''


@contextlib.contextmanager
def stop_signals():
    """SIGINT and SIGTERM noted in the list yielded (their names), not raised, while the block
    runs, so the launcher's loops end at their next turn and stop the nodes; the handlers
    before are restored after. Outside the main thread (no signals there) nothing changes."""
    received: list[str] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def note(signum: int, frame: object) -> None:
        received.append(signal.Signals(signum).name)
    before = {sig: signal.signal(sig, note) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield received
    finally:
        for sig, handler in before.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)   # None: not set from Python


class StackLauncher:
    def __init__(self, parameters: dict[str, dict[str, object]], log_dir: Path):
        self.parameters = parameters
        self.log_dir = log_dir
        self.processes: dict[str, subprocess.Popen] = {}

    def start(self, name: str) -> None:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.processes[name] = start_node(name, self.parameters.get(name, {}), self.log_dir / f'{name}.log')

    def check_alive(self, bridge_too: bool = False) -> None:
        """StackError if a node has exited (the bridge too, if ``bridge_too``): the node, its exit
        code and the last line of its log."""
        for name, process in self.processes.items():
            if process.poll() is not None and (name != BRIDGE or bridge_too):
                log = self.log_dir / f'{name}.log'
                raise StackError(f'{name} exited with code {process.returncode}: '
                                 f'{last_line(log) or "(nothing logged)"} (log: {log})')

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        for process in self.processes.values():
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        for process in self.processes.values():
            try:
                process.wait(max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                process.kill()   # rclpy nodes sometimes ignore SIGINT at exit
                process.wait()
        return {name: process.returncode for name, process in self.processes.items()}


def run_stack(*, mode: str, algorithm: str, episodes: int, seed: int, bag_path: Path, log_dir: Path, modes=(),
              switch_to: str | None = None, switch_at_step: int = 300, timing: str = 'synchronous',
              config_dir: str = '', policy_dir: str = '', extra: dict[str, dict] | None = None,
              timeout: float = 1800.0, visualizer: bool = True, use_sim_time: bool = False,
              thread_priority: int = 0, cpu_split: bool = True, compression: str = 'zstd',
              say: Callable[[str], None] | None = None, progress_every: int = 200,
              step_length: float = 0.1) -> StackRun:
    """Run the stack for ``episodes`` episodes; switch to mode ``switch_to`` at ``switch_at_step``
    of the first episode (through the parameter service); ``modes``: the modes whose policies
    the decision node loads (empty: every mode); ``visualizer``: also publish the
    scene as markers (recorded in the bag); ``use_sim_time``: every node on the bridge's /clock;
    ``thread_priority``: real-time priority of the nodes on the decision path (0: normal);
    ``cpu_split``: the decision path and the onlookers (this launcher's helper node among them)
    on cores of their own; ``compression``: the bag's chunk compression (none, zstd or lz4);
    ``say``: called with a line per phase (nodes up, every ``progress_every`` steps of an
    episode with its mode, the switch asked and where it landed, each episode's end, the bag
    closed), steps shown in seconds with ``step_length``.
    SIGINT or SIGTERM ends the run early (``StackRun.stopped_by``); a node exiting before the
    end raises StackError. Either way every node is stopped and the bag closed."""
    if bag_path.exists():
        raise FileExistsError(f'{bag_path}: the bag directory exists already')
    arguments = {'mode': mode, 'modes': list(modes), 'algorithm': algorithm, 'episodes': episodes, 'seed': seed,
                 'timing': timing, 'bag_path': bag_path, 'visualizer': visualizer, 'use_sim_time': use_sim_time,
                 'config_dir': config_dir, 'policy_dir': policy_dir, 'thread_priority': thread_priority,
                 'cpu_split': cpu_split, 'compression': compression}
    # this launcher's helper node listens to the states too: the bridge waits for it as well
    started = plan(arguments, extra_listeners=1)
    split = cores(arguments)
    parameters = dict(started)
    for name, values in (extra or {}).items():
        parameters[name].update(values)
    nodes = [name for name, _ in started if name != BRIDGE]
    listeners = parameters[BRIDGE]['wait_for_subscribers']
    launcher = StackLauncher(parameters, log_dir)
    run = StackRun(bag_path)
    probe = ProbeNode('stack_launcher')
    node = probe.node
    state = {'step': -1, 'episode': -1, 'ended': 0, 'mode': mode, 'shown': (-1, 0)}
    say = say or (lambda line: None)
    run.switch = None if switch_to is None else SwitchSteps(switch_at_step)

    def on_event(msg: EpisodeEvent) -> None:
        if msg.event == EpisodeEvent.EVENT_ENDED:
            state['ended'] += 1
            run.episodes.append(metrics_from_event(msg))
            say(f'episode {msg.episode} (seed {msg.seed}) ended at step {msg.steps}: Exit-1 rate {msg.p_cav:.2f}, '
                f'CAV collisions {msg.p_collision_cav:.2f}')
        elif msg.event == EpisodeEvent.EVENT_STARTED:
            say(f'episode {msg.episode} (seed {msg.seed}) started in mode {state["mode"]}')

    def on_states(raw: bytes) -> None:   # the progress only: (episode, step) read without decoding
        with contextlib.suppress(InputError):   # a message too short for them is no progress
            state['episode'], state['step'] = episode, step = episode_and_step(raw)
            mark = (episode, step // progress_every)
            if mark[1] and mark != state['shown']:
                state['shown'] = mark
                say(f'episode {episode}: step {step} ({step * step_length:.0f} s simulated), mode {state["mode"]}')

    def on_commands(msg: CavCommandArray) -> None:   # the switch's landing: the first decision in the new mode
        if run.switch and run.switch.requested >= 0 and run.switch.landed < 0 and msg.mode == switch_to:
            run.switch.landed = msg.step
            state['mode'] = switch_to
            say(f'the decision node decides in {switch_to} from step {msg.step} on '
                f'({msg.step * step_length:.1f} s simulated)')

    node.create_subscription(EpisodeEvent, EPISODE_TOPIC, on_event, EVENT_QOS)
    node.create_subscription(VehicleStateArray, STATES_TOPIC, on_states, STREAM_QOS, raw=True)
    if switch_to is not None:
        node.create_subscription(CavCommandArray, COMMANDS_TOPIC, on_commands, STREAM_QOS)
    client = node.create_client(SetParameters, '/decision_node/set_parameters')
    onlooking = contextlib.ExitStack()   # this process back on its cores however the run ends
    # after the helper node's rclpy.init (whose own SIGINT handler would take the signal)
    stopping = onlooking.enter_context(stop_signals())
    try:
        for name in nodes:
            launcher.start(name)
        deadline = time.monotonic() + 120.0
        # the recorder records the markers from the first one on
        while not stopping and (node.count_subscribers(STATES_TOPIC) < listeners or not client.service_is_ready()
                                or 'visualizer' in nodes and node.count_publishers(MARKERS_TOPIC) < 1):
            launcher.check_alive()
            if time.monotonic() > deadline:
                raise StackError(f'the nodes did not come up within 120 s (logs: {log_dir})')
            probe.spin_once(0.2)
        if not stopping:
            say(f'nodes up: {", ".join(nodes)}; starting {BRIDGE} (node logs: {log_dir})')
            launcher.start(BRIDGE)
            # once every node is started: a node takes only cores it could use at its start
            onlooking.enter_context(pinned(split and split[1]))
        switched = switch_to is None
        deadline = time.monotonic() + timeout
        while not stopping and launcher.processes[BRIDGE].poll() is None:
            launcher.check_alive()
            if time.monotonic() > deadline:
                raise StackError(f'the stack did not finish within {timeout} s (logs: {log_dir})')
            probe.spin_once(0.05)
            if not switched and state['episode'] == 0 and state['step'] >= switch_at_step:
                run.switch.requested = state['step']
                say(f'switch {mode} -> {switch_to} asked for at step {switch_at_step}: requested at step '
                    f'{state["step"]} (/decision_node/set_parameters)')
                result = probe.set_parameter(client, 'mode', switch_to, timeout=10.0)
                run.switch.answered = state['step']
                run.mode_switch = (f'mode {mode} -> {switch_to} at step {run.switch.requested}: '
                                   + ('accepted' if result and result.successful else
                                      f'refused ({result.reason if result else "no answer"})'))
                say(f'switch {mode} -> {switch_to}: {run.mode_switch.partition(": ")[2]} (answered by step '
                    f'{state["step"]})')
                switched = True
        if not stopping:
            launcher.check_alive(bridge_too=launcher.processes[BRIDGE].returncode != 0)
        end = time.monotonic() + 5.0   # the last episode event may still be in flight
        while not stopping and state['ended'] < episodes and time.monotonic() < end:
            probe.spin_once(0.1)
        run.stopped_by = stopping[0] if stopping else ''
    finally:
        with onlooking:
            run.return_codes = launcher.stop()
            probe.close()
    if (bag_path / 'metadata.yaml').is_file():   # what the recorder writes last, on closing the bag
        size = sum(path.stat().st_size for path in bag_path.rglob('*') if path.is_file()) if bag_path.is_dir() else 0
        say(f'bag closed: {bag_path} ({size / 1e6:.2f} MB)')
    return run


def free_bag_path(base: Path) -> Path:
    """base, or base_2, base_3, ... : the first that does not exist."""
    path, index = base, 1
    while path.exists():
        index += 1
        path = base.with_name(f'{base.name}_{index}')
    return path
