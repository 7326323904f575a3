"""What the nodes share: topic names, QoS choices, parameters, diagnostics, the main wrapper.

QoS, on purpose, per topic (docs/design.md, "ROS 2", says the same):
- vehicle_states, traffic_graph, cav_commands: reliable (in synchronous mode every message
  of a step matters: a lost command stalls the bridge until its timeout), keep last 1000 on
  both sides in the stack's nodes (``STATES_QOS``, ``GRAPH_QOS``, ``COMMANDS_QOS``). A
  publisher's 1000 is its resend history: a reader that falls behind (a recorder sharing 2
  cores with training: with 10 it lost 30% of the states) catches up without losses. A
  node's 1000 absorbs a stall (the decision node's first policy call; a node left without
  CPU for a while on 2 busy cores, during a flood of 1000 msg/s on its topic) without losing
  the messages of its own stream among the flood. A deep queue does not make answers late
  because a node empties its stream queues at once (``take_waiting``, no executor pass per
  message) and refuses what cannot follow its episode and step from the message's header,
  before decoding it: some 10 us a refused message. Before that, rclpy's executor (0.35 ms
  a message) and its throttled logging (0.37 ms a rejected message) made a node slower than
  a flood of 1000 msg/s, and keep-last, at any depth, dropped or delayed the states and
  commands of the decision steps (56-85 command timeouts an episode). Observers (the
  launcher, the visualizer, tests) take ``STREAM_QOS``, depth 100. Messages lost anyway are
  counted (``dropped_<topic>``, from the publisher's sequence numbers, while a topic has one
  publisher: rclpy does not say which of several publishers a message came from, and its
  message_lost event does not see a reader's keep-last overflow), and the steps missing
  between two a node took as ``skipped_*``.
- the recorder subscribes with depth 1000: it must keep everything, and writing is cheap.
- episode_events: reliable, transient local, depth 50: a late subscriber (the launcher, a
  node restarted mid-episode, a recorder started later) still gets the episode that is
  running (its EVENT_STARTED starts the node's sequence checks) and the metrics of recent ones.
- /clock: best effort, keep last 1 (ROS 2's clock QoS): only the newest time matters.
- /diagnostics: reliable, keep last 10, the /diagnostics convention (one status a second).
"""
from __future__ import annotations

import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from exit_decision.ros.stack import cpu_affinity, realtime
from exit_decision.ros.dds_defaults import apply_dds_defaults

# DDS on loopback and our Fast DDS profile unless the user chose otherwise (dds_defaults), set
# before rclpy starts, in the module every node (run_node), the launcher's and the benchmark's
# helper node (ProbeNode) import; every process they start inherits it.
apply_dds_defaults()

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rcl_interfaces.srv import SetParameters
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidHandle, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from exit_decision.config import ConfigError, ProjectConfig, default_config_dir, load_project  # noqa: E402
from exit_decision.errors import PolicyError  # noqa: E402
from exit_decision.input_checks import InputError  # noqa: E402
from exit_decision.ros.messages.states_cdr import checked_states_cdr  # noqa: E402
from exit_decision.step_gaps import episode_and_step  # noqa: E402

STATES_TOPIC = '/exit_decision/vehicle_states'
GRAPH_TOPIC = '/exit_decision/traffic_graph'
COMMANDS_TOPIC = '/exit_decision/cav_commands'
EPISODE_TOPIC = '/exit_decision/episode_events'
CLOCK_TOPIC = '/clock'
DIAGNOSTICS_TOPIC = '/diagnostics'
MARKERS_TOPIC = '/exit_decision/markers'
OVERRIDES_TOPIC = '/exit_decision/shield_overrides'

STREAM_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=100)
#: what the stack's nodes publish and subscribe states, graph and commands with (see above)
STATES_QOS = GRAPH_QOS = COMMANDS_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE,
                                                   history=HistoryPolicy.KEEP_LAST, depth=1000)
DIAGNOSTICS_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=10)
RECORDER_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=1000)
EVENT_QOS = QoSProfile(reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST, depth=50,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)
CLOCK_QOS = QoSProfile(reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST, depth=1)


def describe(description: str, *, read_only: bool = False, integer_range: tuple[int, int] | None = None,
             float_range: tuple[float, float] | None = None, constraints: str = '') -> ParameterDescriptor:
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=constraints)
    if integer_range is not None:
        descriptor.type = ParameterType.PARAMETER_INTEGER
        descriptor.integer_range = [IntegerRange(from_value=integer_range[0], to_value=integer_range[1], step=1)]
    if float_range is not None:
        descriptor.type = ParameterType.PARAMETER_DOUBLE
        descriptor.floating_point_range = [FloatingPointRange(from_value=float_range[0], to_value=float_range[1])]
    return descriptor


class ParameterError(ValueError):
    """A start-up parameter value a node cannot use; the text names the parameter and what is allowed."""


def allowed_values(descriptor: ParameterDescriptor, default) -> str:
    """What a parameter's descriptor allows, in words."""
    if descriptor.additional_constraints:
        return descriptor.additional_constraints
    if descriptor.integer_range:
        r = descriptor.integer_range[0]
        return f'an integer in {r.from_value}..{r.to_value}'
    if descriptor.floating_point_range:
        r = descriptor.floating_point_range[0]
        return f'a number in [{r.from_value:g}, {r.to_value:g}]'
    kind = {bool: 'true or false', str: 'a string', int: 'an integer', float: 'a number'}
    if isinstance(default, list):
        return f'a list of {kind.get(type(default[0]), "values") if default else "values"}'
    return kind.get(type(default), 'a value of its type')


def declare(node: Node, name: str, default, descriptor: ParameterDescriptor):
    """``node.declare_parameter(...).value``; a value given at start that the type or range
    refuses raises ParameterError naming the parameter and what is allowed."""
    try:
        return node.declare_parameter(name, default, descriptor).value
    except ParameterException:
        given = getattr(node, '_parameter_overrides', {}).get(name)
        shown = repr(given.value) if given is not None else 'the value given'
        raise ParameterError(f'parameter {name}: {shown} is not allowed; allowed: '
                             f'{allowed_values(descriptor, default)}') from None


def follow(node: Node, *names: str) -> None:
    """Apply new values of these parameters at once: ``node.<name>`` takes every accepted value
    (the descriptor's type and range have checked it). Parameters a node reads only at start
    are declared ``read_only`` instead, so a new value is refused rather than ignored."""
    def apply(parameters: list[Parameter]) -> None:
        for parameter in parameters:
            if parameter.name in names:
                setattr(node, parameter.name, parameter.value)
    node.add_post_set_parameters_callback(apply)


def check_choice(name: str, value, choices) -> None:
    """Raise ParameterError unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ParameterError(f'parameter {name}: {value!r} is not allowed; allowed: {" | ".join(choices)}')


def declare_thread_priority(node: Node) -> int:
    """Declare the read-only ``thread_priority`` of a node on the decision path (bridge, graph
    builder, decision node) and apply it to every thread of the process: its own, the
    middleware's, and those it starts later (they inherit it). 0, the default, leaves the
    OS's normal scheduling. 1-99 runs them with real-time SCHED_FIFO at that priority, as
    ros2_control's controller manager runs its loop: on a machine whose cores the onlookers
    (recorder, visualizer) share, a wake-up on the decision path then never waits behind
    another process (docs/design.md, "ROS 2 -> Speed"). Needs the right to: CAP_SYS_NICE, or an
    rtprio limit of at least that priority; without it the node does not start, and says so."""
    priority = declare(node, 'thread_priority', 0, describe(
        realtime.DESCRIPTION, read_only=True, integer_range=(realtime.PRIORITIES[0], realtime.PRIORITIES[-1])))
    if priority:
        try:
            realtime.apply(priority)
        except realtime.RealtimeRefused as refused:
            raise ParameterError(f'parameter thread_priority: {refused}') from None
    return priority


def declare_cpu_affinity(node: Node) -> list[int]:
    """Declare the read-only ``cpu_affinity`` of a node (default: every core the process may use
    at start, so ``ros2 param get`` tells where it runs) and pin every thread of the process to
    those cores: its own, the middleware's, and those it starts later. The stack gives the
    decision path and the onlookers cores of their own (``cpu_split``; ``ros/stack/cpu_affinity.py``
    says why)."""
    cores = declare(node, 'cpu_affinity', cpu_affinity.AT_START, describe(
        cpu_affinity.DESCRIPTION, read_only=True,
        constraints=f'a non-empty list of the cores this process may use, {cpu_affinity.AT_START}'))
    cores = list(cores or [])   # `-p cpu_affinity:=[]` comes as None (no type)
    reason = cpu_affinity.refusal(cores)
    if reason:
        raise ParameterError(f'parameter cpu_affinity: {reason}')
    if sorted(set(cores)) != cpu_affinity.usable():
        cpu_affinity.pin(cores)
    return cores


def declare_config(node: Node) -> ProjectConfig:
    """Declare the read-only ``config_dir`` parameter and load the project config from it."""
    value = declare(node, 'config_dir', '', describe(
        'directory with the YAML config; empty: the installed share/exit_decision/config',
        read_only=True))
    return load_project(Path(value) if value else default_config_dir())


REJECT_LOG_PERIOD = 5.0   # [s] a node logs a rejected message of one kind at most this often


class Diagnostics:
    """Counters a node publishes on /diagnostics once a second (and on demand)."""

    def __init__(self, node: Node, name: str):
        self.node, self.name = node, name
        self.counters: dict[str, float] = {}
        self.figures: list[Callable[[], dict[str, float]]] = []   # more values, computed at each publish
        self.quiet_until: dict[str, float] = {}   # per rejected key: no log line before this (monotonic) time
        self.publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS)
        # once a wall-clock second, also under use_sim_time (stamped with the node's clock)
        node.create_timer(1.0, self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def count(self, key: str, amount: float = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + amount

    def reject(self, key: str, what: str, reason: str) -> None:
        """Count a rejected message under ``rejected_<key>`` and say why, at most once every
        REJECT_LOG_PERIOD seconds per key (throttled here: rclpy's throttle inspects the caller's
        frame on every call, 0.37 ms, which made a flood of rejects cost more than the messages)."""
        self.count(f'rejected_{key}')
        now = time.monotonic()
        if now >= self.quiet_until.get(key, 0.0):
            self.quiet_until[key] = now + REJECT_LOG_PERIOD
            self.node.get_logger().warning(f'rejected {what}: {reason}')

    def step_of(self, raw: bytes, what: str) -> tuple[int, int] | None:
        """(episode, step) from the front of a serialized message (``step_gaps.episode_and_step``);
        None, rejected and counted (``rejected_<what>``), if the bytes are too short to hold them."""
        try:
            return episode_and_step(raw)
        except InputError as error:
            self.reject(what, what, str(error))
            return None

    def out_of_sequence(self, gate, events, episode: int, step: int, what: str) -> bool:
        """Reject and count (``rejected_out_of_sequence_<what>``) a message whose (episode, step)
        ``gate`` (an ``input_checks.StepGate``) refuses; True if it did. A message of another
        episode than the gate's, or a step back (the same episode again: a looped bag's next
        pass), first takes what waits on ``events`` (the episode-events subscription): its
        EVENT_STARTED, from the same bridge or player, came before it."""
        if episode != gate.episode or step <= gate.last:
            take_waiting(events)
        reason = gate.refuse(episode, step)
        if reason:
            self.reject(f'out_of_sequence_{what}', what, reason)
        return reason is not None

    def take_states(self, raw: bytes, gate, events, limits, every: int = 1):
        """The vehicle states in ``raw`` (a ``states_cdr.DecodedStates``), or None when they are
        not taken: a step that is not a multiple of ``every`` (not counted), and, rejected and
        counted, bytes too short for (episode, step), a step ``gate`` refuses (``out_of_sequence``)
        and a field that does not fit the scenario's ``limits``. Read in that order, so a flood
        of what cannot follow costs no decoding. The caller accepts the step on its gate."""
        key = self.step_of(raw, 'states')
        if key is None or key[1] % every:
            return None
        episode, step = key
        if self.out_of_sequence(gate, events, episode, step, 'states'):
            return None
        try:
            return checked_states_cdr(raw, limits)
        except InputError as error:
            self.reject('states', f'states of step {step}', str(error))
            return None

    def subscribe(self, msg_type, topic: str, callback: Callable, qos: QoSProfile, raw: bool = False):
        """``node.create_subscription`` that also counts messages lost before the node took
        them (``dropped_<topic>``): gaps in the publisher's sequence numbers, counted while
        the topic has one publisher (with several, rclpy does not say whose a message is).
        ``raw``: the callback gets the serialized message (to decode only the ones it uses)."""
        key = f'dropped_{topic.rsplit("/", 1)[-1]}'
        last: dict[str, int] = {}
        subscription = None

        def on_message(msg, info) -> None:
            number = info.get('publication_sequence_number')
            if number is not None and subscription.get_publisher_count() == 1:
                previous = last.get('number')
                if previous is not None and number > previous + 1:
                    self.count(key, number - previous - 1)
                last['number'] = number
            else:
                last.clear()
            callback(msg)
        subscription = self.node.create_subscription(msg_type, topic, on_message, qos, raw=raw)
        return subscription

    def publish(self) -> None:
        problems = sum(value for key, value in self.counters.items() if key.startswith('rejected'))
        values = dict(self.counters)
        for figures in self.figures:
            values.update(figures())
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK, name=self.name,
            message=f'{problems:g} rejected messages' if problems else 'ok', hardware_id='exit_decision',
            values=[KeyValue(key=key, value=f'{value:g}') for key, value in sorted(values.items())])
        message = DiagnosticArray(status=[status])
        message.header.stamp = self.node.get_clock().now().to_msg()
        self.publisher.publish(message)


def take_waiting(subscription, limit: int | None = None) -> int:
    """Hand the messages waiting in the queue of ``subscription`` (all, or at most ``limit``) to
    its callback now, without the executor, and say how many (a flood on the topic costs each
    message its decoding, or its header read, and the check that refuses it)."""
    with_info = subscription._callback_type is Subscription.CallbackType.WithMessageInfo   # as rclpy's executor calls it
    taken = 0
    try:
        with subscription.handle:
            while limit is None or taken < limit:
                message = subscription.handle.take_message(subscription.msg_type, subscription.raw)
                if message is None:
                    break
                subscription.callback(*(message if with_info else message[:1]))
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
    set on their subscriptions, services, clients, timers and guard conditions. Each
    subscription that is ready hands over its queue at once, up to its QoS depth a pass
    (``take_waiting``), in the order the nodes (given in order) created them (a node that
    subscribes to the episode events first sees an episode's start before its messages); a
    guard condition's callback runs here (the wait takes its trigger). rclpy's executor
    (``spin_once(0)``) serves the rest: services, clients and timers when they are ready, and
    its own work (tasks of futures, QoS event handlers) at least every ``EXECUTOR_PERIOD``.

    rclpy's executor builds its wait set again, and walks every entity of the node (two QoS
    event handlers per publisher and subscription) in Python, for every single message it
    hands over: 0.35-0.7 ms a message here, most of what the stack's nodes cost per step.
    One thread spins a Waiter (it keeps its wait set between passes)."""

    EXECUTOR_PERIOD = 0.5   # [s]
    #: the node attributes listing what a wait set holds, in the order ``_rclpy.WaitSet`` counts them
    KINDS = ('subscriptions', 'guards', 'timers', 'clients', 'services')

    def __init__(self, nodes: Sequence[Node], executor: SingleThreadedExecutor):
        self.nodes, self.executor = tuple(nodes), executor
        self.executor_passed = time.monotonic()
        self.wait_set, self.wait_set_counts = None, None

    def spin_once(self, timeout_sec: float) -> None:
        """Wait up to ``timeout_sec`` and serve what is ready. Lean because every message of a
        node costs one: the wait set is kept and refilled while the number of entities stays
        (its creation was a fifth of a pass), and the entities are held as rclpy's executor
        holds them (no entity destroyed while waited on), without an ExitStack (a pass cost
        100 us of CPU here, 160 us inside the stack, for every states message of a step)."""
        entities = [[item for node in self.nodes for item in getattr(node, kind)] for kind in self.KINDS]
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
            if counts != self.wait_set_counts:
                self.wait_set = _rclpy.WaitSet(*counts, 0, self.nodes[0].context.handle)   # no events
                self.wait_set_counts = counts
            wait_set = self.wait_set
            wait_set.clear_entities()
            for items, add in zip(entities, (wait_set.add_subscription, wait_set.add_guard_condition,
                                             wait_set.add_timer, wait_set.add_client, wait_set.add_service)):
                for item in items:
                    add(item.handle)
            wait_set.wait(int(timeout_sec * 1e9))
            ready_subscriptions = set(wait_set.get_ready_entities('subscription'))
            ready_guards = set(wait_set.get_ready_entities('guard_condition')) if guards else ()
            others_ready = any(wait_set.get_ready_entities(kind) for kind, items in
                               (('timer', timers), ('client', clients), ('service', services)) if items)
            taken = [item for item in subscriptions if item.handle.pointer in ready_subscriptions]
            triggered = [guard for guard in guards if guard.callback is not None and guard.handle.pointer in ready_guards]
        finally:
            _release(held)
        for subscription in taken:
            take_waiting(subscription, subscription.qos_profile.depth or None)   # keep-all: depth 0
        for guard in triggered:
            guard.callback()
        now = time.monotonic()
        if others_ready or not taken or now - self.executor_passed >= self.EXECUTOR_PERIOD:
            self.executor_passed = now
            self.executor.spin_once(timeout_sec=0.0)

    def keep_serving(self) -> None:
        """For a loop that may not wait for a while (a realtime bridge behind its schedule): a
        pass without waiting if the executor has had none for ``EXECUTOR_PERIOD``, so services
        (``ros2 param set``) are still answered."""
        if time.monotonic() - self.executor_passed >= self.EXECUTOR_PERIOD:
            self.spin_once(0.0)


class ProbeNode:
    """A node inside a non-ROS program (the launcher, a benchmark, a test) with its own
    context and executor, so it never touches the global rclpy context."""

    def __init__(self, name: str):
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.waiter = Waiter([self.node], self.executor)

    def spin_once(self, timeout_sec: float) -> None:
        """Take what is waiting, or wait up to ``timeout_sec`` for something (``Waiter``)."""
        self.waiter.spin_once(timeout_sec)

    def spin_until(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            self.spin_once(0.05)
        return condition()

    def call(self, client, request, timeout: float, attempt: float = 10.0):
        """Call a service through ``client``; its response, or None when no answer came within
        ``timeout`` seconds. A request unanswered after ``attempt`` seconds is sent again (the
        calls made here, getting and setting parameters, are harmless to repeat): right after
        discovery the server's response can be lost before the client's response reader is
        matched (Fast DDS: "failed to send response (timeout)", seen on fresh clones)."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            future = client.call_async(request)
            self.executor.spin_until_future_complete(future, timeout_sec=min(attempt, left))
            if future.done() and future.result():
                return future.result()
            client.remove_pending_request(future)
        return None

    def set_parameter(self, client, name: str, value, timeout: float, attempt: float = 10.0):
        """Call a node's set_parameters service (what `ros2 param set` calls) through ``client``
        (``call``); the SetParametersResult, or None when no answer came within ``timeout`` seconds."""
        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        response = self.call(client, request, timeout, attempt)
        return response.results[0] if response is not None else None

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


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
