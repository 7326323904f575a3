"""``bench ros``: the ROS 2 stack's speed, measured from outside its processes (an observer
node, /proc), and the /proc readings it and the recorder's memory test share."""
from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path


def bench_ros(config_dir: str, policy_dir: str, steps: int, seed: int, thread_priority: int = 0,
              cpu_split: bool = True) -> str:
    """The default stack (``node_table.plan``: recorder and visualizer included), each row of
    the table its own process, synchronous mode, episodes until stopped.

    The other processes and the bridge start first; once they are up the one with the decision
    node starts, and an observer node measures from that moment the first answer of its
    get_parameters service, the bridge's first step (it waits for the decision node's commands
    publisher, which comes once the policies are loaded) and the first command. Then, from the
    first command on, ``steps`` steps: steps/s, the real-time factor and the state-to-command
    latency: the synchronous bridge's own wait for a decision step's commands (from its
    /diagnostics, a second after the steps), and for each decision step the time from the
    observer receiving the states to it receiving the commands (its receive stamps lag when its
    cores are busy) and from the states written to the commands written (source stamps); each
    process's CPU time per step over those steps (from /proc: where the cores' time goes, which
    wall-clock figures on a shared machine hide), its resident memory at the first command and
    after the steps, and the cores its threads may run on.
    ``thread_priority``: the nodes on the decision path run real-time at it, and so does the
    observer once they are started (its receive stamps must not lag theirs), until it returns
    (0: normal scheduling). ``cpu_split``: the stack's default, the decision path and the
    onlookers on cores of their own (normal scheduling only); the observer, an onlooker, is on
    the onlookers' cores once the nodes are started, until it returns."""
    import tempfile

    import numpy as np
    from diagnostic_msgs.msg import DiagnosticArray
    from exit_decision_msgs.msg import CavCommandArray, VehicleStateArray
    from rcl_interfaces.srv import GetParameters
    from rclpy.serialization import deserialize_message

    from exit_decision.ros.stack import cpu_affinity, realtime
    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.topics import COMMANDS_TOPIC, DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC, STATES_TOPIC, STREAM_QOS
    from exit_decision.ros.stack.launcher import StackLauncher
    from exit_decision.ros.stack.node_table import BRIDGE, cores, plan, process_of
    from exit_decision.step_gaps import episode_and_step

    # (episode, step) -> when the observer's middleware received it (its receive stamp, so the
    # observer's own executor, which may lag on 2 busy cores, does not count), and when its
    # publisher wrote it (its source stamp: no delivery, to the observer or anyone)
    states_at: dict[tuple[int, int], float] = {}
    commands_at: dict[tuple[int, int], float] = {}
    written: dict[str, dict[tuple[int, int], float]] = {'states': {}, 'commands': {}}
    counted = {'states': 0, 'step_length': 0.0}   # states received since the first command
    probe = ProbeNode('bench_observer')
    node = probe.node

    # the observer reads only (episode, step) of the messages (raw): decoding every one would
    # load the 2 cores it measures on
    def on_states(raw: bytes, info) -> None:
        key = episode_and_step(raw)
        states_at[key], written['states'][key] = info['received_timestamp'] * 1e-9, info['source_timestamp'] * 1e-9
        counted['states'] += bool(commands_at)
        counted['step_length'] = counted['step_length'] or deserialize_message(raw, VehicleStateArray).step_length

    def on_commands(raw: bytes, info) -> None:
        key = episode_and_step(raw)
        commands_at[key], written['commands'][key] = info['received_timestamp'] * 1e-9, info['source_timestamp'] * 1e-9

    node.create_subscription(VehicleStateArray, STATES_TOPIC, on_states, STREAM_QOS, raw=True)
    node.create_subscription(CavCommandArray, COMMANDS_TOPIC, on_commands, STREAM_QOS, raw=True)
    bridge_figures: dict[str, float] = {}   # the bridge's newest values on /diagnostics

    def on_diagnostics(msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == BRIDGE:
                bridge_figures.clear()
                bridge_figures.update({value.key: float(value.value) for value in status.values})
                bridge_figures['received'] = time.monotonic()

    node.create_subscription(DiagnosticArray, DIAGNOSTICS_TOPIC, on_diagnostics, DIAGNOSTICS_QOS)
    parameters_client = node.create_client(GetParameters, '/decision_node/get_parameters')
    answered = {'at': 0.0}
    cpu_at_first_command: dict[str, float] = {}
    memory_at_first_command: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as onlooking:
        arguments = {'episodes': 0, 'seed': seed, 'bag_path': Path(tmp) / 'bag', 'config_dir': config_dir,
                     'policy_dir': policy_dir, 'thread_priority': thread_priority, 'cpu_split': cpu_split}
        started = plan(arguments, extra_listeners=1)
        split = cores(arguments)
        names = [name for name, _ in started]
        deciding = process_of('decision_node', names)   # started last, timed
        launcher = StackLauncher(dict(started), Path(tmp) / 'logs')
        try:
            for name in names:
                if name != deciding:
                    launcher.start(name)
            others = sum(1 for name in names if name not in (BRIDGE, deciding))
            deadline = time.monotonic() + 120
            while node.count_subscribers(STATES_TOPIC) < others + 1 and time.monotonic() < deadline:
                launcher.check_alive()
                probe.spin_once(0.1)
            decision_start = time.time()
            launcher.start(deciding)
            onlooking.enter_context(cpu_affinity.pinned(split and split[1]))   # every node started (see run_stack)
            if thread_priority:   # the observer too, its children started: its receive stamps must not lag theirs
                realtime.apply(thread_priority)
            pending = None
            deadline = time.monotonic() + 600
            while counted['states'] < steps + 1 and time.monotonic() < deadline:
                launcher.check_alive()
                if not answered['at'] and parameters_client.service_is_ready() and pending is None:
                    pending = parameters_client.call_async(GetParameters.Request(names=['mode']))
                if pending is not None and not answered['at'] and pending.done():   # polled: no executor task late
                    answered['at'] = time.time()
                if commands_at and not cpu_at_first_command:
                    cpu_at_first_command = process_cpu_seconds(launcher)
                    memory_at_first_command = process_memory_mb(launcher)
                probe.spin_once(0.01)
            cpu_used = {name: seconds - cpu_at_first_command.get(name, 0.0)
                        for name, seconds in process_cpu_seconds(launcher).items()}
            steps_done = time.monotonic()   # the bridge's figures of a later second cover these steps
            while bridge_figures.get('received', 0.0) < steps_done + 0.1 and time.monotonic() < steps_done + 3.0:
                probe.spin_once(0.05)
            memory_at_end = process_memory_mb(launcher)
            cores_used = process_cores(launcher)
        finally:
            launcher.stop()
            probe.close()
            if thread_priority:
                realtime.reset()
    first_command = min(commands_at.values())
    window = sorted(at for at in states_at.values() if at >= first_command)[:steps + 1]
    elapsed, measured = window[-1] - window[0], len(window) - 1
    answered_steps = [key for key in commands_at if key in states_at and window[0] <= states_at[key] <= window[-1]]

    def spread(values: np.ndarray) -> str:
        return f'median {np.median(values):.2f} ms, p99 {np.percentile(values, 99):.2f} ms'

    latency = np.array([(commands_at[key] - states_at[key]) * 1000 for key in answered_steps])
    written_latency = np.array([(written['commands'][key] - written['states'][key]) * 1000 for key in answered_steps])
    answer = f'{answered["at"] - decision_start:.2f} s' if answered['at'] else '(no answer)'
    core_count = len(os.sched_getaffinity(0))
    return '\n'.join([
        (f'ROS 2 stack, {len(names)} processes ({", ".join(names)}), synchronous, '
         + (f'decision path at real-time priority {thread_priority}, ' if thread_priority else 'normal scheduling, ')
         + (f'decision path on cores {split[0]}, onlookers on {split[1]}, ' if split else 'no core split, ')
         + f'{measured} steps ({len(latency)} decisions) from the first command'),
        (f'  decision node start: parameters answered after {answer}, '
         f'the bridge\'s first step after {min(states_at.values()) - decision_start:.2f} s, '
         f'first command after {first_command - decision_start:.2f} s'),
        f'  steps/s {measured / elapsed:.0f}, real-time factor {measured * counted["step_length"] / elapsed:.1f}x',
        ('  states -> commands latency, the bridge\'s own wait from publishing the states to the commands '
         f'accepted (its last {bridge_figures["decision_wait_steps"]:.0f} decision steps, on /diagnostics): median '
         f'{bridge_figures["decision_wait_ms_median"]:.2f} ms, p99 {bridge_figures["decision_wait_ms_p99"]:.2f} ms, '
         f'max {bridge_figures["decision_wait_ms_max"]:.2f} ms' if 'decision_wait_steps' in bridge_figures
         else '  states -> commands latency, the bridge\'s own wait: (no /diagnostics from the bridge)'),
        f'    the observer\'s, from its receive stamps (late when its cores are busy): {spread(latency)}',
        f'    from the publishers\' source stamps (states written -> commands written): {spread(written_latency)}',
        '  CPU per step [ms]: ' + ', '.join(f'{name} {seconds * 1000 / measured:.2f}' for name, seconds in
                                            sorted(cpu_used.items(), key=lambda item: -item[1])) +
        f' (sum {sum(cpu_used.values()) * 1000 / measured:.2f} of the {core_count * 1000 * elapsed / measured:.2f} '
        f'that {core_count} cores have per step at this rate)',
        '  resident memory [MB] at the first command -> after the steps: ' + ', '.join(
            f'{name} {memory_at_first_command[name]:.0f} -> {memory_at_end[name]:.0f}'
            for name in memory_at_end if name in memory_at_first_command),
        '  cores of their threads: ' + ', '.join(f'{name} {allowed}' for name, allowed in cores_used.items())])


def proc_files(launcher, file: str) -> dict[str, str]:
    """``/proc/<pid>/<file>`` of each running process of the launcher (one that has ended is left out)."""
    texts = {}
    for name, process in launcher.processes.items():
        try:
            texts[name] = Path(f'/proc/{process.pid}/{file}').read_text()
        except OSError:   # it has ended
            pass
    return texts


def resident_mb(status: str) -> float:
    """Resident memory (VmRSS) [MB] in the text of a ``/proc/<pid>/status``."""
    return next(int(line.split()[1]) for line in status.splitlines() if line.startswith('VmRSS:')) / 1024


def process_memory_mb(launcher) -> dict[str, float]:
    """Resident memory (VmRSS) of each running process of the launcher: a long ``bench ros``
    shows whether a node's memory grows with the steps (the recorder's must not)."""
    return {name: resident_mb(status) for name, status in proc_files(launcher, 'status').items()}


def process_cores(launcher) -> dict[str, list[int]]:
    """The cores any thread of each running process of the launcher, and of this process
    (``observer``), may run on: what ``cpu_split`` and the nodes' ``cpu_affinity`` gave them."""
    pids = {'observer': os.getpid(), **{name: process.pid for name, process in launcher.processes.items()}}
    cores = {}
    for name, pid in pids.items():
        allowed = set()
        try:
            for thread in os.listdir(f'/proc/{pid}/task'):
                with contextlib.suppress(OSError):   # it ended meanwhile
                    allowed |= os.sched_getaffinity(int(thread))
        except OSError:   # the process has ended
            continue
        cores[name] = sorted(allowed)
    return cores


def process_cpu_seconds(launcher) -> dict[str, float]:
    """CPU time (user + system) each running process of the launcher has used, and this
    process's own (``observer``: the benchmark's probe)."""
    ticks = os.sysconf('SC_CLK_TCK')
    used = {'observer': time.process_time()}
    for name, stat in proc_files(launcher, 'stat').items():
        fields = stat.rsplit(')', 1)[1].split()
        used[name] = (int(fields[11]) + int(fields[12])) / ticks   # utime, stime (fields 14, 15 of stat)
    return used
