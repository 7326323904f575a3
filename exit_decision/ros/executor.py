"""How a process runs its nodes: the lean wait on their entities (``Waiter``), spin, and ``run_node``, the main."""
from __future__ import annotations

import signal
import sys
import threading
import time
import weakref
from collections.abc import Callable, Sequence

from exit_decision.ros.dds_defaults import apply_dds_defaults

# DDS on loopback and our Fast DDS profile unless the user chose otherwise (dds_defaults), set
# before rclpy starts, in the module every node (run_node) and the helper node of the launcher,
# the benchmark and the tests (probe.ProbeNode, through Waiter) import; every process they
# start inherits it.
apply_dds_defaults()

import rclpy  # noqa: E402
from rclpy.callback_groups import CallbackGroup  # noqa: E402
from rclpy.exceptions import InvalidHandle  # noqa: E402
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor  # noqa: E402
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from rclpy.subscription import Subscription  # noqa: E402

from exit_decision.config import ConfigError  # noqa: E402
from exit_decision.errors import ParameterError, PolicyError  # noqa: E402
from exit_decision.ros.take import MESSAGE_WAITING, QUEUE_EMPTY, UNBOUNDED, SerializedTake  # noqa: E402


class TakenByTheWaiter(CallbackGroup):
    """The callback group of the stack's subscriptions (``intake.Intake``): rclpy's executor
    leaves them alone, so every message of theirs is taken by ``take_waiting``, with its
    publisher's gid (a message the executor took would come without it)."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


_takes = threading.local()   # a thread's SerializedTake (its buffer), made on its first raw take
#: subscription -> [ns, system clock] when the last ``take_waiting`` that emptied its queue began
_emptied: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def emptied_at(subscription) -> int:
    """[ns, the system clock of the middleware's reception stamps] when the last ``take_waiting``
    that emptied the queue of ``subscription`` began (-1: none yet): every message the node had
    received by then has been taken."""
    return _emptied.get(subscription, -1)


def take_waiting(subscription, limit: int | None = None) -> int:
    """Hand the messages waiting in the queue of ``subscription`` (all, or at most ``limit``) to
    its callback now, without the executor, and say how many were taken. A raw subscription's
    messages are taken with their publisher's gid, in C (``take.SerializedTake``): the bounds an
    ``intake.Intake`` subscription carries on its callback (``intake.Bounded``: a size limit, a
    window of steps) drop what they refuse there, counted by them, so a flood of such messages
    costs each no Python; the rest reach the callback one by one."""
    with_info = subscription._callback_type is Subscription.CallbackType.WithMessageInfo   # as rclpy's executor calls it
    callback, taken, began = subscription.callback, 0, time.time_ns()
    try:
        with subscription.handle:
            if not subscription.raw:
                while limit is None or taken < limit:
                    message = subscription.handle.take_message(subscription.msg_type, False)
                    if message is None:
                        _emptied[subscription] = began
                        break
                    callback(*(message if with_info else message[:1]))
                    taken += 1
                return taken
            if not hasattr(_takes, 'take'):
                _takes.take = SerializedTake()
            take, bounds = _takes.take, getattr(callback, 'bounds', UNBOUNDED)
            while limit is None or taken < limit:
                # the window asked again each time: a callback may have moved it
                status, dropped = take.drain(subscription, bounds.size_limit, bounds.window(),
                                             limit - taken if limit else 0)
                if dropped:
                    bounds.dropped(take.records(dropped), dropped)
                    taken += dropped
                if status == QUEUE_EMPTY:
                    _emptied[subscription] = began
                    break
                if status == MESSAGE_WAITING:
                    message = take.waiting()
                    callback(*(message if with_info else message[:1]))
                    taken += 1
    except InvalidHandle:   # destroyed (by an earlier callback of this pass)
        pass
    return taken


def _release(handles) -> None:
    """Exit every entered entity handle, each even when one before it raises (the first error
    is raised after all), as an ExitStack would."""
    error = None
    for handle in handles:
        try:
            handle.__exit__(None, None, None)
        except Exception as failed:  # noqa: BLE001 (re-raised below, after the others are released)
            error = error or failed
    if error is not None:
        raise error


class Waiter:
    """The wait of a process's nodes (one, or several composed in one process), lean: one wait
    set on their subscriptions and guard conditions, and at least every ``SERVICE_PERIOD`` on
    their services, clients and timers too. Each subscription that is ready hands over its
    queue at once, up to its QoS depth a pass (``take_waiting``), in the order the nodes (given
    in order) created them (a node that subscribes to the episode events first sees an
    episode's start before its messages); a guard condition's callback runs here (the wait
    takes its trigger). rclpy's executor (``spin_once(0)``) serves the rest: services, clients
    and timers when they are ready, and its own work (tasks of futures, QoS event handlers) at
    least every ``EXECUTOR_PERIOD``.

    rclpy's executor builds its wait set again, and walks every entity of the node (two QoS
    event handlers per publisher and subscription) in Python, for every single message it
    hands over: 0.35-0.7 ms a message here, most of what the stack's nodes cost per step.
    One thread spins a Waiter (it keeps its wait sets between passes).

    Why services wait for their turn: the middleware's wait costs each entity waited on its
    attachment and detachment (the bridge's 8 services and timers make its pass about twice as
    costly as one on its one subscription), and a node that a flood wakes thousands of times a
    second pays that at every wake. So a busy node answers a service request within
    ``SERVICE_PERIOD``; one with nothing to take waits on everything, and answers at once."""

    EXECUTOR_PERIOD = 0.5   # [s]
    SERVICE_PERIOD = 0.02   # [s] services, clients and timers are waited on at least this often
    #: the node attributes listing what a wait set holds, in the order ``_rclpy.WaitSet`` counts
    #: them; a pass between SERVICE_PERIODs waits on the first two kinds only
    KINDS = ('subscriptions', 'guards', 'timers', 'clients', 'services')

    def __init__(self, nodes: Sequence[Node], executor: SingleThreadedExecutor):
        self.nodes, self.executor = tuple(nodes), executor
        self.executor_passed = time.monotonic()
        self.everything_due = 0.0                      # (monotonic) the next pass waits on every kind
        self.wait_sets: dict[bool, tuple] = {}         # everything? -> (its entity counts, its wait set)

    def entities(self, kinds) -> list[list]:
        """The nodes' entities of each of ``KINDS``: those of ``kinds``, none of the others."""
        return [[item for node in self.nodes for item in getattr(node, kind)] if kind in kinds else []
                for kind in self.KINDS]

    def spin_once(self, timeout_sec: float) -> None:
        """Wait up to ``timeout_sec`` and serve what is ready. Lean because every message of a
        node costs one: the wait set is kept and refilled while the number of entities stays
        (its creation was a fifth of a pass), services wait for their turn (class docstring),
        and the entities are held as rclpy's executor holds them (no entity destroyed while
        waited on), without an ExitStack (a pass cost 100 us of CPU here, 160 us inside the
        stack, for every states message of a step)."""
        now = time.monotonic()
        everything = now >= self.everything_due
        entities = self.entities(self.KINDS if everything else self.KINDS[:2])
        if not any(entities):   # nothing to wait on between the services' turns: their turn now
            everything, entities = True, self.entities(self.KINDS)
        held = []
        try:
            for items in entities:
                kept = []
                for item in items:
                    try:
                        item.handle.__enter__()
                    except InvalidHandle:
                        continue
                    held.append(item.handle)
                    kept.append(item)
                items[:] = kept
            subscriptions, guards, timers, clients, services = entities
            counts = tuple(map(len, entities))
            kept_counts, wait_set = self.wait_sets.get(everything, (None, None))
            if counts != kept_counts:
                wait_set = _rclpy.WaitSet(*counts, 0, self.nodes[0].context.handle)   # no events
                self.wait_sets[everything] = counts, wait_set
            wait_set.clear_entities()
            for items, add in zip(entities, (wait_set.add_subscription, wait_set.add_guard_condition,
                                             wait_set.add_timer, wait_set.add_client, wait_set.add_service)):
                for item in items:
                    add(item.handle)
            wait_set.wait(int((timeout_sec if everything else min(timeout_sec, self.everything_due - now)) * 1e9))
            ready_subscriptions = wait_set.get_ready_entities('subscription')   # a few: a list is as quick as a set
            ready_guards = wait_set.get_ready_entities('guard_condition') if guards else ()
            others_ready = everything and any(wait_set.get_ready_entities(kind) for kind, items in
                                              (('timer', timers), ('client', clients), ('service', services)) if items)
            taken = [item for item in subscriptions if item.handle.pointer in ready_subscriptions]
            triggered = [guard for guard in guards if guard.callback is not None and guard.handle.pointer in ready_guards]
        finally:
            _release(held)
        for subscription in taken:
            take_waiting(subscription, subscription.qos_profile.depth or None)   # keep-all: depth 0
        for guard in triggered:
            guard.callback()
        if not everything:
            return
        now = time.monotonic()
        self.everything_due = now + self.SERVICE_PERIOD
        if others_ready or not taken or now - self.executor_passed >= self.EXECUTOR_PERIOD:
            self.executor_passed = now
            self.executor.spin_once(timeout_sec=0.0)

    def keep_serving(self) -> None:
        """For a loop that may not wait for a while (a realtime bridge behind its schedule): a
        pass without waiting if the executor has had none for ``EXECUTOR_PERIOD``, so services
        (``ros2 param set``) are still answered."""
        if time.monotonic() - self.executor_passed >= self.EXECUTOR_PERIOD:
            self.everything_due = 0.0
            self.spin_once(0.0)


_STOP_SIGNALS: list[int] = []   # SIGINT/SIGTERM received by this process


def _interrupt(signum: int, frame: object) -> None:
    _STOP_SIGNALS.append(signum)
    raise KeyboardInterrupt


def spin(nodes: Sequence[Node]) -> None:
    """``rclpy.spin`` of a process's nodes, lean (``Waiter``), that wakes at least twice a second,
    so Ctrl-C or SIGTERM stops them even when nothing else would wake them (under use_sim_time
    with no /clock no timer ever fires)."""
    executor = SingleThreadedExecutor(context=nodes[0].context)
    for node in nodes:
        executor.add_node(node)
    waiter = Waiter(nodes, executor)
    while nodes[0].context.ok():
        waiter.spin_once(0.5)


def run_node(name: str, make_node: Callable[[], Node | Sequence[Node]],
             run: Callable[[Node], None] | None = None) -> int:
    """Standard main: init, make the node (or the nodes composed in this process, in the order
    their subscriptions are served), spin (or ``run`` the one node), clean shutdown on
    Ctrl-C/SIGTERM.

    A node that cannot start (bad config, missing or corrupt policy) says why and exits with 1."""
    # KeyboardInterrupt on SIGINT and SIGTERM (ours, noting the signal), instead of rclpy's, which
    # would invalidate the context before the node's clean-up (the recorder closing its bag).
    rclpy.init(args=sys.argv, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    nodes: Sequence[Node] = ()
    try:
        made = make_node()
        nodes = [made] if isinstance(made, Node) else list(made)
        if run is not None:
            run(*nodes)
        else:
            spin(nodes)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ConfigError, PolicyError, ParameterError) as error:   # before RuntimeError: PolicyError is one
        print(f'[{name}] cannot start: {error}', file=sys.stderr)
        return 1
    except RuntimeError:
        # a KeyboardInterrupt raised while rclpy's C++ converts a message comes out as
        # "RuntimeError: Unable to convert call argument": a stop all the same
        if not _STOP_SIGNALS:
            raise
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
