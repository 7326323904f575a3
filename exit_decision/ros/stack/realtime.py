"""Real-time scheduling for the nodes on the decision path (their ``thread_priority``
parameter, ``stack`` / ``bench ros --thread-priority``), free of rclpy so the command line can
check it before it starts anything.

SCHED_FIFO is applied to every thread of the process: its own, the middleware's, and those
started later, which inherit it (docs/design.md, "ROS 2 -> Speed", says why and what it gives).
"""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Callable


#: what the parameter (and launch argument, and command-line option) allows, and says
PRIORITIES = range(0, 100)
DESCRIPTION = ('real-time (SCHED_FIFO) priority 1-99 of every thread of the nodes on the decision path (bridge, '
               'graph builder, decision node); 0: normal scheduling. Needs CAP_SYS_NICE or an rtprio limit >= the '
               'priority (ulimit -r)')


class RealtimeRefused(PermissionError):
    """This process may not use real-time scheduling; the text says why and how to allow it."""


def each_thread(apply: Callable[[int], None]) -> None:
    """``apply(thread id)`` for every thread of this process (one that ends meanwhile is skipped)."""
    for thread in os.listdir('/proc/self/task'):
        with contextlib.suppress(ProcessLookupError):
            apply(int(thread))


def _all_threads(policy: int, priority: int) -> None:
    each_thread(lambda thread: os.sched_setscheduler(thread, policy, os.sched_param(priority)))


def apply(priority: int) -> None:
    """Every thread of this process SCHED_FIFO at ``priority`` (1-99); RealtimeRefused when the
    kernel says no."""
    if not hasattr(os, 'sched_setscheduler') or not os.path.isdir('/proc/self/task'):
        raise RealtimeRefused(f'{priority} needs Linux real-time scheduling, which this system lacks; allowed here: 0')
    try:
        _all_threads(os.SCHED_FIFO, priority)
    except PermissionError:
        import resource
        limit = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
        shown = 'unlimited' if limit == resource.RLIM_INFINITY else limit
        raise RealtimeRefused(
            f'{priority} needs real-time scheduling rights, which this process lacks (the kernel refused: its '
            f'rtprio limit is {shown}, and without CAP_SYS_NICE, or in a cgroup with no real-time CPU time, '
            f'that is what it allows); allowed: 0, or grant them (an rtprio limit >= {priority} in '
            f'/etc/security/limits.conf, or CAP_SYS_NICE)') from None


def reset() -> None:
    """Every thread of this process back to the normal scheduling (always allowed)."""
    _all_threads(os.SCHED_OTHER, 0)


def refusal(priority: int) -> str | None:
    """Why a process started from here could not run at ``priority`` (None if it could): tried
    in a throwaway child, so this process keeps its scheduling."""
    result = subprocess.run([sys.executable, '-c', f'from exit_decision.ros.stack.realtime import apply; apply({priority})'],
                            capture_output=True, text=True, check=False)
    if result.returncode == 0:
        return None
    lines = result.stderr.strip().splitlines()
    return lines[-1].partition(': ')[2] if lines else f'exit code {result.returncode}'
