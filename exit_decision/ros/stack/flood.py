"""``bench flood``: the default stack (synchronous, as fast as it goes) while each topic its nodes
subscribe to is flooded in turn from other processes, with stale and with oversized messages
(``flooder.py``), at ``rate_factor`` (10) x the stack's own rate of vehicle-state messages,
measured in the same run before the floods.

Each (topic, kind) runs ``pairs`` interleaved pairs of phases: a flood of ``phase_seconds``, then
as long without one; the wait's p99 pools a (topic, kind)'s pairs. An observer node (through the
intake, as the nodes) measures:
- the rate each flood reached (what the flooders sent over their time) against the target;
- the bridge's decision wait per decision step, from the source stamps of the states it
  publishes: the time from the states of a decision step to the states of the next step (the
  bridge's wait for the commands, plus one simulation step); its p99 in the flood phases over
  its p99 in the phases between;
- every node's counters on /diagnostics: its command timeouts, and per flood whether every
  subscriber counted every message (oversized: ``dropped_<topic>_too_large``; stale: taken,
  ``received_<topic>``, each then used or dropped with a cause);
- every node's peak resident memory (VmHWM of /proc: the most it ever had);
- and that no node died (the run stops with the node's last log line if one does).
"""
from __future__ import annotations

import contextlib
import json
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from exit_decision.ros.topic_names import CLOCK_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC, MARKERS_TOPIC

RATE_FACTOR = 10.0
WAIT_RATIO = 1.5           # the flood's p99 decision wait over the quiet one's, at most
MEMORY_MB = 400.0          # every node's resident memory, at most
HUGE_BYTES_PER_S = 50e6    # [B/s] the huge oversized messages' share of a flood, about
RATE_MARGIN = 1.05         # the flooders aim this much over the target (a sender behind catches up late)
FLOODER_START = 4.0        # [s] after their start the flooders begin together (imports, discovery)
KINDS = ('stale', 'oversized')
#: topics whose stale messages a node takes rather than drops: no step to be out of sequence
#: with (an episode's start announced again, a time, a parameter change, counters, markers)
TAKEN_WHEN_STALE = (EPISODE_TOPIC, CLOCK_TOPIC, '/parameter_events', DIAGNOSTICS_TOPIC, MARKERS_TOPIC)


@dataclass
class Phase:
    topic: str
    kind: str
    target: float                 # [msg/s]
    sent: int = 0
    bytes: int = 0
    error: str = ''               # a flooder that failed: what it said
    refused: int = 0              # messages the flooders' own middleware would not send (none reached the stack)
    rate: float = 0.0             # [msg/s] reached: the flooders' rates (each its sent over its time), summed
    window: tuple[float, float] = (0.0, 0.0)     # wall clock of the flood
    quiet: tuple[float, float] = (0.0, 0.0)      # wall clock of the phase without it
    counted: dict[str, dict[str, float]] = field(default_factory=dict)   # node -> counter -> increase


@dataclass
class FloodRun:
    state_rate: float = 0.0
    phases: list[Phase] = field(default_factory=list)
    decision_steps: dict[tuple[int, int], float] = field(default_factory=dict)  # decision step -> its wait [s]
    decided_at: dict[tuple[int, int], float] = field(default_factory=dict)      # decision step -> when (wall)
    peak_mb: dict[str, float] = field(default_factory=dict)
    subscribers: dict[str, list[str]] = field(default_factory=dict)   # topic -> the nodes subscribing to it
    command_timeouts: float = 0.0
    rate_factor: float = RATE_FACTOR

    def waits(self, windows) -> np.ndarray:
        """[ms] the decision waits of the steps decided in these (start, end) windows."""
        return np.array([self.decision_steps[key] * 1000 for key, at in self.decided_at.items()
                         if any(start <= at <= end for start, end in windows)])

    def uncounted(self, phase: Phase) -> dict[str, float]:
        """Node -> flood messages of the phase it did not count (0: every one): oversized, those
        it did not count as too large; stale, those it neither dropped with a cause nor recorded
        (on a topic whose stale messages are taken, not dropped: those it did not take); in both,
        those it counted as lost before it took them (gaps in a publisher's sequence). The
        stack's own messages of the phase count too, so a loss smaller than them goes unseen."""
        from exit_decision.ros.diagnostics import CAUSES, drop_key
        name = phase.topic.rsplit('/', 1)[-1]
        missing = {}
        for node in self.subscribers[phase.topic]:
            counters = phase.counted.get(node, {})
            if phase.kind == 'oversized':
                got = counters.get(f'dropped_{name}_too_large', 0.0)
            elif phase.topic in TAKEN_WHEN_STALE:
                got = counters.get(f'received_{name}', 0.0)
            else:
                got = sum(counters.get(drop_key(phase.topic, cause), 0.0) for cause in CAUSES)
                got += counters.get(f'recorded_{name}', 0.0)
            got += counters.get(f'dropped_{name}', 0.0)
            missing[node] = max(phase.sent - got, 0.0)
        return missing


def bench_flood(config_dir: str = '', policy_dir: str = '', seed: int = 10000, phase_seconds: float = 3.0,
                pairs: int = 1, topics: list[str] | None = None, kinds=KINDS, flooders: int = 2,
                rate_factor: float = RATE_FACTOR, huge_bytes_per_s: float = HUGE_BYTES_PER_S) -> FloodRun:
    """Run the stack and its floods (module docstring); the figures (``report`` prints them)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from exit_decision_msgs.msg import VehicleStateArray

    from exit_decision.config import default_config_dir, load_project
    from exit_decision.ros.diagnostics import Diagnostics
    from exit_decision.ros.intake import Intake
    from exit_decision.ros.messages.sizes import limits_of
    from exit_decision.ros.probe import ProbeNode
    from exit_decision.ros.stack.bench import proc_files
    from exit_decision.ros.stack.launcher import StackLauncher
    from exit_decision.ros.stack import cpu_affinity
    from exit_decision.ros.stack.node_table import BRIDGE, ENDPOINTS, NODE_NAMES, cores, plan
    from exit_decision.ros.topics import DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC, STATES_TOPIC, STREAM_QOS
    from exit_decision.step_gaps import episode_and_step

    config = load_project(Path(config_dir) if config_dir else default_config_dir())
    limits, interval = limits_of(config), config.env.decision_interval
    run = FloodRun(rate_factor=rate_factor)
    written: dict[tuple[int, int], float] = {}   # (episode, step) -> source stamp of its states [s]
    newest: dict[str, tuple[float, dict[str, float]]] = {}   # node -> (received at, counters)
    probe = ProbeNode('flood_observer')
    intake = Intake(probe.node, Diagnostics(probe.node, 'flood_observer'), limits)

    def on_states(raw: bytes, info) -> None:
        episode, step = episode_and_step(raw)
        if episode == 0:   # the stale flood's episode: the measures start with episode 1
            return
        written[(episode, step)] = info['source_timestamp'] * 1e-9

    def on_diagnostics(msg) -> None:
        for status in msg.status:
            values = {}
            for value in status.values:
                try:
                    values[value.key] = float(value.value)
                except ValueError:
                    pass
            newest[status.name] = (time.time(), values)

    intake.subscribe(VehicleStateArray, STATES_TOPIC, on_states, STREAM_QOS, raw=True, with_info=True)
    intake.subscribe(DiagnosticArray, DIAGNOSTICS_TOPIC, on_diagnostics, DIAGNOSTICS_QOS)

    def spin(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            launcher.check_alive(bridge_too=True)
            probe.spin_once(0.02)

    def counters_after(moment: float) -> dict[str, dict[str, float]]:
        """Every node's counters of a /diagnostics message received after ``moment`` (wall)."""
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and not all(newest.get(node, (0.0,))[0] > moment for node in nodes):
            spin(0.05)
        return {node: dict(newest.get(node, (0.0, {}))[1]) for node in nodes}

    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as onlooking:
        arguments = {'episodes': 0, 'seed': seed, 'bag_path': Path(tmp) / 'bag', 'config_dir': config_dir,
                     'policy_dir': policy_dir}
        started = plan(arguments, extra_listeners=1)
        split = cores(arguments)
        names = [name for name, _ in started]
        nodes = [node for name in names for node in NODE_NAMES[name]]
        subscribed = sorted({topic for node in nodes for topic in ENDPOINTS[node].subscribes})
        run.subscribers = {topic: [node for node in nodes if topic in ENDPOINTS[node].subscribes]
                           for topic in subscribed}
        flooded = [topic for topic in subscribed if topics is None or topic in topics]
        launcher = StackLauncher(dict(started), Path(tmp) / 'logs')
        try:
            for name in names:
                if name != BRIDGE:
                    launcher.start(name)
            listeners = dict(started)[BRIDGE]['wait_for_subscribers']
            deadline = time.monotonic() + 120
            while probe.node.count_subscribers(STATES_TOPIC) < listeners and time.monotonic() < deadline:
                launcher.check_alive()
                probe.spin_once(0.1)
            launcher.start(BRIDGE)
            onlooking.enter_context(cpu_affinity.pinned(split and split[1]))   # the observer: an onlooker
            # the stack's own rate: from episode 1 on (the stale flood's episode is 0), over a phase
            deadline = time.monotonic() + 300
            while not written and time.monotonic() < deadline:
                spin(0.1)
            spin(phase_seconds)
            stamps = sorted(written.values())
            run.state_rate = (len(stamps) - 1) / max(stamps[-1] - stamps[0], 1e-9) if len(stamps) > 1 else 0.0
            target = rate_factor * run.state_rate
            before = counters_after(time.time())
            timeouts_before = before.get(BRIDGE, {}).get('command_timeouts', 0.0)
            for topic in flooded:
                for kind in kinds:
                    for _ in range(pairs):
                        phase = Phase(topic, kind, target)
                        readers = len(run.subscribers[topic]) + (topic in (STATES_TOPIC, DIAGNOSTICS_TOPIC))
                        flood(phase, limits[topic], config, flooders, readers, phase_seconds, spin, huge_bytes_per_s)
                        phase.quiet = (phase.window[1] + 0.5, phase.window[1] + 0.5 + phase_seconds)
                        spin(0.5 + phase_seconds)
                        after = counters_after(max(phase.quiet[1], time.time()))
                        phase.counted = {node: {key: value - before.get(node, {}).get(key, 0.0)
                                                for key, value in after[node].items()} for node in nodes}
                        before = after
                        run.phases.append(phase)
            run.command_timeouts = before.get(BRIDGE, {}).get('command_timeouts', 0.0) - timeouts_before
            for name, status in proc_files(launcher, 'status').items():
                run.peak_mb[name] = next(int(line.split()[1]) for line in status.splitlines()
                                         if line.startswith('VmHWM:')) / 1024
        finally:
            launcher.stop()
            probe.close()
    for (episode, step), at in written.items():
        after = written.get((episode, step + 1))
        if step % interval == 0 and after is not None:
            run.decision_steps[(episode, step)] = after - at
            run.decided_at[(episode, step)] = at
    return run


def flood(phase: Phase, limit: int, config, flooders: int, subscribers: int, seconds: float, spin,
          huge_bytes_per_s: float) -> None:
    """One flood of ``phase`` from ``flooders`` processes; its sent messages, bytes and window."""
    from exit_decision.ros.stack.flooder import HUGE_SIDE

    huge_every = max(2, math.ceil(phase.target * HUGE_SIDE * HUGE_SIDE / huge_bytes_per_s)) if huge_bytes_per_s \
        else 0   # none
    command = [sys.executable, '-m', 'exit_decision.ros.stack.flooder', phase.topic, phase.kind,
               '--rate', str(phase.target * RATE_MARGIN / flooders), '--seconds', str(seconds), '--limit', str(limit),
               '--num-nodes', str(config.graph.max_vehicles), '--feature-set', config.graph.feature_set,
               '--huge-every', str(huge_every), '--subscribers', str(subscribers)]
    command += ['--start-at', str(time.time() + FLOODER_START)]
    # on the onlookers' cores (the stack's cpu_split), as the observer whose affinity they inherit:
    # what sending the flood costs the attacker is not the stack's cost, what the stack does with it is
    processes = [subprocess.Popen(command, stdout=subprocess.PIPE, text=True) for _ in range(flooders)]
    while any(process.poll() is None for process in processes):
        spin(0.05)
    reports = []
    for process in processes:
        out = process.stdout.read().strip().splitlines()
        if process.returncode or not out:
            phase.error = f'a flooder failed with code {process.returncode}'
            continue
        reports.append(json.loads(out[-1]))
    if not reports:
        return
    phase.sent = sum(report['sent'] for report in reports)
    phase.bytes = sum(report['bytes'] for report in reports)
    phase.refused = sum(report['refused'] for report in reports)
    phase.window = (max(report['start'] for report in reports), min(report['end'] for report in reports))
    phase.rate = sum(report['sent'] / max(report['end'] - report['start'], 1e-9) for report in reports)


def unsendable(phase: Phase) -> bool:
    """Whether no message of the flood could be sent at all: the flooders' middleware refused every
    one (an oversized flood of a bounded type, /clock's: Fast DDS sends no sample over the type's
    size). Such a flood cannot happen, so it has no rate or wait to judge."""
    return phase.sent == 0 and phase.refused > 0 and not phase.error


def report(run: FloodRun) -> tuple[str, bool]:
    """The figures of a run, and whether it met every target."""
    ok = True
    lines = [f'flood bench: the stack\'s own rate {run.state_rate:.0f} states/s, the floods\' target '
             f'{run.rate_factor:g}x = {run.rate_factor * run.state_rate:.0f} msg/s; '
             f'{len(run.decision_steps)} decision steps measured']
    pairs: dict[tuple[str, str], list[Phase]] = {}
    for phase in run.phases:
        pairs.setdefault((phase.topic, phase.kind), []).append(phase)
    # the p99 of the decision waits in every flood of a topic and kind, over those between them:
    # one 3-s window's p99 is its 3rd-5th longest wait, and two quiet windows differ by up to 3x
    waits = {key: (run.waits([each.window for each in group]), run.waits([each.quiet for each in group]))
             for key, group in pairs.items()}
    for phase in run.phases:
        group = pairs[(phase.topic, phase.kind)]
        flood_waits, quiet_waits = waits[(phase.topic, phase.kind)]
        p99 = (float(np.percentile(flood_waits, 99)) if len(flood_waits) else math.nan,
               float(np.percentile(quiet_waits, 99)) if len(quiet_waits) else math.nan)
        ratio = p99[0] / p99[1] if p99[1] else math.nan
        missing = run.uncounted(phase)
        if unsendable(phase):
            lines.append(f'  {phase.topic} {phase.kind}: not applicable: the flooders\' middleware refused to send '
                         f'every one of {phase.refused} (a bounded type: none of its messages is over its limit)')
            continue
        if phase.error:
            ok = False
            lines.append(f'  {phase.topic} {phase.kind}: FAILED, {phase.error}')
        rate_ok, wait_ok = phase.rate >= phase.target, ratio <= WAIT_RATIO
        counted_ok = not any(missing.values())
        ok &= rate_ok and wait_ok and counted_ok and len(flood_waits) > 0
        name = phase.topic.rsplit('/', 1)[-1]
        lines.append(
            f'  {phase.topic} {phase.kind}: {phase.rate:.0f} msg/s ({phase.bytes / 1e6 / max(phase.window[1] - phase.window[0], 1e-9):.1f} MB/s)'
            f' {"reached" if rate_ok else "BELOW"} the target {phase.target:.0f}; decision wait p99 '
            f'{p99[0]:.2f} ms in the flood ({len(flood_waits)} steps), {p99[1]:.2f} ms without ({len(quiet_waits)} '
            f'steps){f", its {len(group)} pairs pooled" if len(group) > 1 else ""}: {ratio:.2f}x '
            f'{"ok" if wait_ok else "OVER " + str(WAIT_RATIO) + "x"}')
        causes = {node: {key.removeprefix(f'dropped_{name}_'): value for key, value in counters.items()
                         if key.startswith(f'dropped_{name}_') and value}
                  for node, counters in phase.counted.items() if node in run.subscribers[phase.topic]}
        unsent = f' ({phase.refused} more the flooders\' middleware would not send)' if phase.refused else ''
        lines.append(f'    {phase.sent} sent{unsent}; dropped by cause: ' + '; '.join(
            f'{node} {", ".join(f"{cause} {value:.0f}" for cause, value in sorted(by.items())) or "none"}'
            for node, by in causes.items()) + ('; every one counted by every subscriber' if counted_ok else
                                               '; NOT COUNTED: ' + ', '.join(f'{node} {value:.0f}'
                                                                             for node, value in missing.items() if value)))
    memory_ok = all(mb < MEMORY_MB for mb in run.peak_mb.values())
    timeouts_ok = run.command_timeouts == 0
    ok &= memory_ok and timeouts_ok
    lines.append('  peak resident memory [MB]: ' + ', '.join(f'{name} {mb:.0f}' for name, mb in run.peak_mb.items())
                 + (f' (every one under {MEMORY_MB:.0f})' if memory_ok else f' (OVER {MEMORY_MB:.0f})'))
    lines.append(f'  command timeouts: {run.command_timeouts:.0f}; no node died')
    lines.append('flood bench: ' + ('every target met' if ok else 'FAILED (see the lines above)'))
    return '\n'.join(lines), ok
