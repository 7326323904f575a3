"""A node's counters (rejected, dropped, skipped messages and its own figures) on /diagnostics."""
from __future__ import annotations

import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile

from exit_decision.input_checks import InputError
from exit_decision.ros.executor import take_waiting
from exit_decision.ros.messages.states_cdr import checked_states_cdr
from exit_decision.ros.topics import DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC
from exit_decision.step_gaps import episode_and_step

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
