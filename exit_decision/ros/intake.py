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
``take_waiting``), and copies a message over its topic's limit no further than the middleware
did (``take.Unread``: its length only). ``topics.py``
says what each queue holds at most of accepted messages: depth x the topic's limit.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping

from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message

from exit_decision.ros.diagnostics import Diagnostics
from exit_decision.ros.executor import TakenByTheWaiter
from exit_decision.ros.messages.sizes import DEFAULT_LIMIT, limits_of

#: rmw's RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED (UINT64_MAX)
SEQUENCE_NUMBER_UNSUPPORTED = 2 ** 64 - 1
#: publishers whose last sequence number a subscription keeps (the most recent): the intake's
#: memory stays bounded however many publishers come and go
MAX_PUBLISHERS = 256


def short(topic: str) -> str:
    """The last part of a topic's name, as the counters name it (``vehicle_states``)."""
    return topic.rsplit('/', 1)[-1]


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
                  with_info: bool = False):
        """``node.create_subscription`` through the intake: ``callback`` gets the message (the
        serialized bytes if ``raw``; and its rclpy message info if ``with_info``) only if it is
        within the topic's limit and, typed, decodes. Every message taken is counted
        (``received_<topic>``), before any check."""
        name, limit, diagnostics = short(topic), self.limit(topic), self.diagnostics
        lost, received = f'dropped_{name}', f'received_{name}'
        last: dict[bytes, int] = {}   # publisher gid -> the sequence number of its last message taken

        def on_message(data: bytes, info) -> None:
            diagnostics.count(received)
            number, gid = info.get('publication_sequence_number'), info.get('publisher_gid')
            if gid is not None and number is not None and number != SEQUENCE_NUMBER_UNSUPPORTED:
                previous = last.pop(gid, None)   # popped and put back: the dict keeps the latest publishers last
                if previous is not None and number > previous + 1:
                    diagnostics.count(lost, number - previous - 1)
                last[gid] = number
                if len(last) > MAX_PUBLISHERS:
                    del last[next(iter(last))]
            if len(data) > limit:
                diagnostics.drop(topic, 'too_large', f'a message on {topic}',
                                 f'{len(data)} bytes, more than its limit of {limit}')
                return
            if raw:
                callback(data, info) if with_info else callback(data)
                return
            try:
                message = deserialize_message(data, msg_type)
            except Exception as error:  # noqa: BLE001 (rclpy raises several kinds on bad CDR; all are a drop)
                diagnostics.drop(topic, 'undecodable', f'a message on {topic}', f'not a {msg_type.__name__}: {error}')
                return
            callback(message, info) if with_info else callback(message)
        on_message.size_limit = limit   # take_waiting copies no message over it (``take.Unread``)
        return self.node.create_subscription(msg_type, topic, on_message, qos, raw=True,
                                             callback_group=self.callback_group)
