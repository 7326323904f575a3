"""Which cores a node's threads run on: the nodes' ``cpu_affinity`` parameter and the stack's
``cpu_split``. Free of rclpy, so the launch file, the launcher and the benchmark compute the
stack's split as the nodes check it.

The split gives the decision path (bridge, graph builder, decision node) the first half of the
cores the stack may use and the onlookers (recorder, visualizer, the launcher's and the
benchmark's helper nodes) the rest. Measured on 2 cores (docs/design.md, "ROS 2 -> Speed"):
with every process free to run anywhere, a thread of the path woken while both cores were busy
was queued behind an onlooker on one core and waited there for milliseconds after the other
core had gone idle; on cores of its own no onlooker takes them from it (the path's own
processes, and any other program of the machine, still share them). No privilege is needed.
Not with real-time priority: it preempts the onlookers anyway, and on its share of the cores
the path would keep them busy, so the kernel's reservation for the normal tasks of a core (50
ms a second) would stop it at times (stalls of 56 ms measured).
"""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterable, Iterator

from exit_decision.ros.stack.realtime import each_thread

DESCRIPTION = ('cores every thread of the process runs on, a list such as [0] (taskset); default: every core it may '
               'use at start')
SPLIT_DESCRIPTION = ('true: with the normal scheduling (thread_priority 0), the decision path (bridge, graph '
                     'builder, decision node) on the first half of the cores the stack may use, the recorder and the '
                     'visualizer on the rest (none with 1 core); false, or a real-time thread_priority: every node on '
                     'every core')


def usable() -> list[int]:
    """The cores this process may run on now, in order."""
    return sorted(os.sched_getaffinity(0))


#: the cores this process could run on when it started (before any node pinned it): a node's
#: default, and what it may choose from
AT_START = usable()


def split(cores: Iterable[int]) -> tuple[list[int], list[int]] | None:
    """(the decision path's cores, the onlookers' cores) of these, or None with fewer than 2."""
    cores = sorted(cores)
    if len(cores) < 2:
        return None
    half = (len(cores) + 1) // 2
    return cores[:half], cores[half:]


def refusal(cores: Iterable[int]) -> str | None:
    """Why this process cannot run on ``cores`` (None if it can): what is allowed, in words."""
    cores, allowed = list(cores), AT_START
    if cores and set(cores) <= set(allowed):
        return None
    return f'{cores} is not allowed; allowed: a non-empty list of the cores this process may use, {allowed}'


def pin(cores: Iterable[int]) -> None:
    """Every thread of this process, and those it starts later (they inherit it), on ``cores``."""
    cores = set(cores)
    each_thread(lambda thread: os.sched_setaffinity(thread, cores))


@contextlib.contextmanager
def pinned(cores: Iterable[int] | None) -> Iterator[None]:
    """This process on ``cores`` (None: unchanged) while the block runs, then where it was."""
    if cores is None:
        yield
        return
    before = usable()
    pin(cores)
    try:
        yield
    finally:
        pin(before)
