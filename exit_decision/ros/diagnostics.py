"""A node's counters (rejected, dropped, skipped messages and its own figures) on /diagnostics.

Every message a node drops whole is counted per topic and cause, ``dropped_<topic>_<cause>``
(``CAUSES``; ``ros/intake.py``), beside the finer ``rejected_<what>`` counters of its checks."""
from __future__ import annotations

import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from exit_decision_msgs.msg import EpisodeEvent
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from exit_decision.input_checks import InputError
from exit_decision.ros.executor import emptied_at, take_waiting
from exit_decision.ros.messages.events_cdr import decode_event
from exit_decision.ros.messages.states_cdr import decode_states
from exit_decision.ros.topics import DIAGNOSTICS_QOS, DIAGNOSTICS_TOPIC, EPISODE_TOPIC, GRAPH_TOPIC, STATES_TOPIC
from exit_decision.step_gaps import episode_and_step

REJECT_LOG_PERIOD = 5.0   # [s] a node logs a rejected message of one kind at most this often
#: why a message is dropped whole (``dropped_<topic>_<cause>``): over the topic's size limit,
#: bytes that are no such message, a step that cannot follow the episode and step, a field that
#: does not fit the scenario
CAUSES = ('too_large', 'undecodable', 'out_of_sequence', 'invalid')
DROP_SUFFIXES = tuple(f'_{cause}' for cause in CAUSES)
#: the kinds of message a node checks against its step gate, and their topics
STEPPED = {'states': STATES_TOPIC, 'graphs': GRAPH_TOPIC}


def drop_key(topic: str, cause: str) -> str:
    """The counter of messages of ``topic`` dropped for ``cause``: ``dropped_<last part>_<cause>``."""
    return f'dropped_{topic.rsplit("/", 1)[-1]}_{cause}'


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

    def reject(self, key: str, what: str, reason: str, topic: str | None = None, cause: str = 'invalid',
               amount: int = 1) -> None:
        """Count a rejected message (or ``amount`` alike) under ``rejected_<key>`` and say why, at most once every
        REJECT_LOG_PERIOD seconds per key (throttled here: rclpy's throttle inspects the caller's
        frame on every call, 0.37 ms, which made a flood of rejects cost more than the messages).
        A message of ``topic`` dropped whole is counted by ``cause`` too (``drop``)."""
        self.count(f'rejected_{key}', amount)
        if topic is not None:
            self.count(drop_key(topic, cause), amount)
        self.log_rejected(key, what, reason)

    def drop(self, topic: str, cause: str, what: str, reason: str, amount: int = 1) -> None:
        """Count a message of ``topic`` (or ``amount`` alike) dropped for ``cause`` (one of ``CAUSES``)
        under ``dropped_<topic>_<cause>`` and say why (throttled as ``reject``)."""
        self.count(drop_key(topic, cause), amount)
        self.log_rejected(f'{topic} {cause}', what, reason)

    def log_rejected(self, key: str, what: str, reason: str) -> None:
        now = time.monotonic()
        if now >= self.quiet_until.get(key, 0.0):
            self.quiet_until[key] = now + REJECT_LOG_PERIOD
            self.node.get_logger().warning(f'rejected {what}: {reason}')

    def step_of(self, raw: bytes, what: str, topic: str | None = None) -> tuple[int, int] | None:
        """(episode, step) from the front of a serialized message (``step_gaps.episode_and_step``);
        None, rejected and counted (``rejected_<what>``; of ``topic``: undecodable), if the bytes
        are too short to hold them."""
        try:
            return episode_and_step(raw)
        except InputError as error:
            self.reject(what, what, str(error), topic, 'undecodable')
            return None

    def episode_starts(self, announce: Callable[[int], None]) -> Callable[[bytes], None]:
        """The callback of a raw subscription to the episode events: each start, read from the
        bytes (``events_cdr``: a flood of events costs each its few fields' reading), is handed
        to ``announce`` (its episode); bytes that are no such message are rejected and counted
        (``rejected_episode_events``, ``dropped_episode_events_undecodable``)."""
        def on_event(raw: bytes) -> None:
            try:
                episode, event = decode_event(raw)
            except InputError as error:
                self.reject('episode_events', 'an episode event', str(error), EPISODE_TOPIC, 'undecodable')
                return
            if event == EpisodeEvent.EVENT_STARTED:
                announce(episode)
        return on_event

    def out_of_sequence(self, gate, events, episode: int, step: int, what: str, received: int | None = None) -> bool:
        """Reject and count (``rejected_out_of_sequence_<what>``, ``dropped_<topic>_out_of_sequence``
        of its topic, ``STEPPED``) a message of ``what`` whose (episode, step)
        ``gate`` (an ``input_checks.StepGate``) refuses; True if it did. A message of another
        episode than the gate's, or a step back (the same episode again: a looped bag's next
        pass), first takes what waits on ``events`` (the episode-events subscription): its
        EVENT_STARTED, from the same bridge or player, came before it. Not when that queue was
        emptied after the message was ``received`` (the middleware's reception stamp, ns): the
        event reached the node before it (one participant's messages come through one port, in
        order), so it was taken then, and a flood of stale messages costs no take of the events
        each."""
        if (episode != gate.episode or step <= gate.last) and (received is None or received >= emptied_at(events)):
            take_waiting(events)
        reason = gate.refuse(episode, step)
        if reason:
            self.reject(f'out_of_sequence_{what}', what, reason, STEPPED[what], 'out_of_sequence')
        return reason is not None

    def take_states(self, raw: bytes, gate, events, limits, every: int = 1, received: int | None = None):
        """The vehicle states in ``raw`` (a ``states_cdr.DecodedStates``), or None when they are
        not taken: a step that is not a multiple of ``every`` (not counted), and, rejected and
        counted, bytes too short for (episode, step), a step ``gate`` refuses (``out_of_sequence``)
        and a field that does not fit the scenario's ``limits``. Read in that order, so a flood
        of what cannot follow costs no decoding (``received``: as ``out_of_sequence``). The caller
        accepts the step on its gate."""
        key = self.step_of(raw, 'states', STATES_TOPIC)
        if key is None or key[1] % every:
            return None
        episode, step = key
        if self.out_of_sequence(gate, events, episode, step, 'states', received):
            return None
        cause = 'undecodable'   # bytes that are no well-formed VehicleStateArray, then fields off the scenario
        try:
            states = decode_states(raw, limits.highway_edges)
            cause = 'invalid'
            limits.check(states.vehicles, step=states.step, step_length=states.step_length)
            return states
        except InputError as error:
            self.reject('states', f'states of step {step}', str(error), STATES_TOPIC, cause)
            return None

    def publish(self) -> None:
        problems = sum(value for key, value in self.counters.items()
                       if key.startswith('rejected') or key.startswith('dropped_') and key.endswith(DROP_SUFFIXES))
        values = dict(self.counters)
        for figures in self.figures:
            values.update(figures())
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK, name=self.name,
            message=f'{problems:g} rejected or dropped messages' if problems else 'ok', hardware_id='exit_decision',
            values=[KeyValue(key=key, value=f'{value:g}') for key, value in sorted(values.items())])
        message = DiagnosticArray(status=[status])
        message.header.stamp = self.node.get_clock().now().to_msg()
        self.publisher.publish(message)
