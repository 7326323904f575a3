"""Bounded intake: the one way a node of the stack subscribes (every node, every topic, typed
messages included), so what arrives is bounded in size before anything reads it, and every
message dropped is counted by cause on /diagnostics.

Each subscription takes the serialized message (rclpy ``raw=True``) and, in this order:
- counts it (``received_<topic>``);
- counts the messages lost before the node took them (``dropped_<topic>``: gaps in each
  publisher's sequence numbers; the node takes its messages with their publisher's gid,
  ``take.SerializedTake``, since rclpy's take does not say whose a message is). A message lost
  before a publisher's first one taken, or after its last, shows no gap and is not counted;
- refuses one over the topic's size limit unread (``dropped_<topic>_too_large``; the limits:
  ``messages/sizes.py``, from the graph's N and the message layout);
- given the node's window of steps, refuses one whose header's (episode, step) is outside it,
  counted by the node (``dropped_<topic>_out_of_sequence``);
- for a typed callback, decodes it (rclpy's ``deserialize_message``) and refuses bytes that are
  no such message (``dropped_<topic>_undecodable``); a raw callback decodes what it uses itself
  and counts the same cause (``Diagnostics.reject`` with ``topic``).
The nodes' own checks then drop what cannot follow the episode and step
(``dropped_<topic>_out_of_sequence``) or does not fit the scenario (``dropped_<topic>_invalid``).

The middleware cannot refuse a large sample earlier here: Fast DDS refuses a sample over a
reader's payload size only with preallocated history memory, whose size rmw_fastrtps takes from
the type's fixed part (a few bytes for the stack's unbounded arrays), not from a limit of ours
(config/fastdds.xml). So a reader's queue holds, while the node has not taken them, up to its
depth of messages of any size; the node empties its queues at once (``executor.Waiter``,
``take_waiting``). The size and the window are checked in C as each message is taken
(``take.SerializedTake.drain``): a message refused there is copied no further than the
middleware did and costs no Python but its counting. ``topics.py`` says what each queue holds at
most of accepted messages: depth x the topic's limit.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping

from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message

from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import TakenByTheWaiter
from exit_decision.ros.messages.sizes import DEFAULT_LIMIT, limits_of
from exit_decision.ros.take import TOO_LARGE, Bounds

#: rmw's RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED (UINT64_MAX)
SEQUENCE_NUMBER_UNSUPPORTED = 2 ** 64 - 1
#: publishers whose last sequence number a subscription keeps (the most recent): the intake's
#: memory stays bounded however many publishers come and go
MAX_PUBLISHERS = 256


def short(topic: str) -> str:
    """The last part of a topic's name, as the counters name it (``vehicle_states``)."""
    return topic.rsplit('/', 1)[-1]


class Bounded(Bounds):
    """One subscription of the intake: what reaches its callback (within ``size_limit``; with a
    ``window``, only messages in the (episode, step) range it returns, checked on the header in
    C: ``take.SerializedTake.drain``), and the counting of every message taken: received, the
    gaps of each publisher's sequence numbers, the drops by cause."""

    def __init__(self, topic: str, size_limit: int, diagnostics: Diagnostics,
                 window: Callable[[], tuple[int, int, int] | None] | None = None,
                 refuse: Callable[[int, int, int], None] | None = None):
        self.topic, self.size_limit, self.diagnostics = topic, size_limit, diagnostics
        self.window_of, self.refuse = window, refuse
        name = short(topic)
        self.lost, self.received = f'dropped_{name}', f'received_{name}'
        self.last: dict[bytes, int] = {}   # publisher gid -> the sequence number of its last message taken

    def window(self) -> tuple[int, int, int] | None:
        return self.window_of() if self.window_of is not None else None

    def sequence(self, gid: bytes | None, number: int | None) -> None:
        """Count the messages of publisher ``gid`` lost before the one numbered ``number``."""
        if gid is None or number is None or number == SEQUENCE_NUMBER_UNSUPPORTED:
            return
        previous = self.last.pop(gid, None)   # popped and put back: the dict keeps the latest publishers last
        if previous is not None and number > previous + 1:
            self.diagnostics.count(self.lost, number - previous - 1)
        self.last[gid] = number
        if len(self.last) > MAX_PUBLISHERS:
            del self.last[next(iter(self.last))]

    def dropped(self, records, count: int) -> None:
        """Count what ``drain`` dropped: received, its publishers' gaps, too large (with its
        length, said once) or outside the window (handed to ``refuse`` with the last one's
        episode and step and how many)."""
        self.diagnostics.count(self.received, count)
        too_large = outside = 0
        for gid, number, cause, first, second in records:
            self.sequence(gid, number)
            if cause == TOO_LARGE:
                too_large, length = too_large + 1, first
            else:
                outside, episode, step = outside + 1, first, second
        if too_large:
            self.diagnostics.drop(self.topic, 'too_large', f'a message on {self.topic}',
                                  f'{length} bytes, more than its limit of {self.size_limit}', too_large)
        if outside:
            self.refuse(episode, step, outside)


class Intake:
    """A node's subscriptions, each bounded (``subscribe``), its drops counted on ``diagnostics``."""

    def __init__(self, node: Node, diagnostics: Diagnostics, limits: Mapping[str, int]):
        self.node, self.diagnostics, self.limits = node, diagnostics, dict(limits)
        self.callback_group = TakenByTheWaiter()

    @classmethod
    def of_config(cls, node: Node, diagnostics: Diagnostics, config) -> Intake:
        """A stack node's intake: the limits of ``config``'s graph and layouts (``messages.sizes``)."""
        return cls(node, diagnostics, limits_of(config))

    def limit(self, topic: str) -> int:
        """[bytes] the most a message on ``topic`` may have (``DEFAULT_LIMIT`` for a topic of others)."""
        return self.limits.get(topic, DEFAULT_LIMIT)

    def subscribe(self, msg_type, topic: str, callback: Callable, qos: QoSProfile, raw: bool = False,
                  with_info: bool = False, window: Callable[[], tuple[int, int, int] | None] | None = None,
                  refuse: Callable[[int, int, int], None] | None = None):
        """``node.create_subscription`` through the intake: ``callback`` gets the message (the
        serialized bytes if ``raw``; and its rclpy message info if ``with_info``) only if it is
        within the topic's limit, typed, decodes, and, given a ``window`` (a function: the
        (episode, first step, last step) the node can take now, or None for any), is in it or has
        no header to tell: ``refuse`` (episode, step, how many) is told of those outside it, the
        node's count and reason. Every message taken is counted (``received_<topic>``), before
        any check (``Bounded``)."""
        if (window is None) != (refuse is None):
            raise ValueError(f'{topic}: a window of steps needs a refusal for what is outside it, and only then')
        bounds = Bounded(topic, self.limit(topic), self.diagnostics, window, refuse)
        diagnostics = self.diagnostics

        def on_message(data: bytes, info) -> None:
            diagnostics.count(bounds.received)
            bounds.sequence(info.get('publisher_gid'), info.get('publication_sequence_number'))
            if raw:
                callback(data, info) if with_info else callback(data)
                return
            try:
                message = deserialize_message(data, msg_type)
            except Exception as error:  # noqa: BLE001 (rclpy raises several kinds on bad CDR; all are a drop)
                diagnostics.drop(topic, 'undecodable', f'a message on {topic}', f'not a {msg_type.__name__}: {error}')
                return
            callback(message, info) if with_info else callback(message)
        on_message.bounds = bounds   # take_waiting drains the queue through them
        return self.node.create_subscription(msg_type, topic, on_message, qos, raw=True,
                                             callback_group=self.callback_group)
