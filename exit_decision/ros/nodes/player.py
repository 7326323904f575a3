"""player: republishes a bag's topics with their recorded timing (and so its /clock).

Messages go out serialized, exactly as recorded, ``rate`` times as fast as recorded
(``rate`` can change while playing: it applies from the next message). ``loop`` plays the
bag again and again. The nodes follow an episode only from its first states after its
EVENT_STARTED, so the player sends each episode's start before the episode's first states,
on every pass: the bag's own event, moved ahead if the recorder wrote it after them, or one
made here if the bag has none. So a bag played twice, or looped, is decided again, not
refused as already seen. While playing, the node answers parameter requests (its executor
spins between messages).

A ``bag_path`` that is empty, missing or not a readable bag stops the player with one line
naming the parameter, and exit code 1.
"""
from __future__ import annotations

import time
from collections import deque
from pathlib import Path

import rclpy
from exit_decision_msgs.msg import EpisodeEvent, VehicleStateArray
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader

from exit_decision.ros.bags.storage import (BAG_ALLOWED, READ_ERRORS, BagError, first_line, message_class, open_bag,
                                            topic_qos)
from exit_decision.ros.executor import run_node
from exit_decision.errors import ParameterError
from exit_decision.ros.parameters import declare, declare_cpu_affinity, describe, follow
from exit_decision.ros.topics import EPISODE_TOPIC, EVENT_QOS, STATES_TOPIC

PASS_SETTLE = 0.5   # [s] between two passes of a looped bag (see let_the_pass_settle)

class Player(Node):
    def __init__(self):
        super().__init__('player')
        declare_cpu_affinity(self)
        self.path = Path(declare(self, 'bag_path', '', describe('bag to play', read_only=True,
                                                                 constraints=BAG_ALLOWED)))
        self.rate = declare(self, 'rate', 1.0, describe('playback speed factor; applies from the next message',
                                                        float_range=(0.01, 1000.0)))
        self.loop = declare(self, 'loop', False, describe('play the bag again when it ends (until stopped or '
                                                          'set false)'))
        self.wait_for_subscribers = declare(self, 'wait_for_subscribers', 0, describe(
            'before playing, wait (up to 30 s) until every topic has this many subscribers; 0: '
            'half a second for discovery', read_only=True, integer_range=(0, 100)))
        follow(self, 'rate', 'loop')
        self.reader().close()   # a bag that cannot be opened stops the node here, before anything is published
        self.executor_ = SingleThreadedExecutor(context=self.context)
        self.executor_.add_node(self)

    def reader(self) -> Reader:
        """The bag, open."""
        try:
            return open_bag(self.path)
        except BagError as error:
            raise ParameterError(f'parameter bag_path: {error}') from None

    def play(self) -> None:
        try:
            publishers = self.wait_for_peers()
            passes = 0
            while rclpy.ok(context=self.context) and (passes == 0 or self.loop):
                if passes:
                    self.let_the_pass_settle(publishers)
                self.play_once(publishers)
                passes += 1
        except ParameterError:
            raise
        except READ_ERRORS as error:
            raise ParameterError(f'parameter bag_path: {self.path}: the bag is corrupt ({first_line(error)}); '
                                 f'allowed: {BAG_ALLOWED}') from None

    def wait_for_peers(self) -> dict:
        """A publisher per topic of the bag, once subscribers can have matched, and one for episode events."""
        reader = self.reader()
        try:
            publishers = {c.topic: self.create_publisher(message_class(c.msgtype), c.topic, topic_qos(c.topic))
                          for c in reader.connections}
        finally:
            reader.close()
        deadline = time.monotonic() + (30.0 if self.wait_for_subscribers else 0.5)
        while rclpy.ok(context=self.context) and time.monotonic() < deadline and (
                not self.wait_for_subscribers or any(p.get_subscription_count() < self.wait_for_subscribers
                                                     for p in publishers.values())):
            self.executor_.spin_once(timeout_sec=0.05)   # let subscribers match: a reliable volatile topic does not resend
        if EPISODE_TOPIC not in publishers:   # for the starts made here (transient local: no need to wait)
            publishers[EPISODE_TOPIC] = self.create_publisher(EpisodeEvent, EPISODE_TOPIC, EVENT_QOS)
        return publishers

    def let_the_pass_settle(self, publishers: dict) -> None:
        """Before a pass starts its episodes again: the last pass's messages delivered and given
        time to be handled, so the passes stay apart on every topic (a node takes the last steps
        of the pass before as that pass's until the next pass's first message begins it; one of
        them that arrived after it would be refused)."""
        for publisher in publishers.values():
            publisher.wait_for_all_acked(Duration(seconds=1.0))
        deadline = time.monotonic() + PASS_SETTLE
        while rclpy.ok(context=self.context) and (left := deadline - time.monotonic()) > 0:
            self.executor_.spin_once(timeout_sec=min(left, 0.1))   # parameter requests meanwhile

    @staticmethod
    def start_episode(events, raw: bytes) -> None:
        """Send an EVENT_STARTED and let it arrive before the episode's states, as the bridge does
        (the nodes start their sequence checks on it; else a pass's first states could come
        before it and be refused as not following the previous pass)."""
        events.publish(raw)
        events.wait_for_all_acked(Duration(seconds=1.0))

    def play_once(self, publishers: dict) -> None:
        """One pass through the bag."""
        published = 0
        events = publishers[EPISODE_TOPIC]
        reader = self.reader()
        try:
            starts: dict[int, deque] = {}   # episode -> the bag's EVENT_STARTED messages, in order
            recorded_events = [c for c in reader.connections if c.topic == EPISODE_TOPIC]
            for _, _, raw in reader.messages(connections=recorded_events) if recorded_events else ():
                event = deserialize_message(bytes(raw), EpisodeEvent)
                if event.event == EpisodeEvent.EVENT_STARTED:
                    starts.setdefault(event.episode, deque()).append(bytes(raw))
            episode, sent_ahead = None, False   # the episode started last in this pass; its bag event already sent
            due, previous = time.monotonic(), None   # when the previous message went out; its bag time
            for connection, timestamp, raw in reader.messages():
                if not rclpy.ok(context=self.context):
                    break
                gap = 0 if previous is None else (timestamp - previous) / 1e9
                while rclpy.ok(context=self.context) and (wait := due + gap / self.rate - time.monotonic()) > 0:
                    self.executor_.spin_once(timeout_sec=min(wait, 0.1))   # rate may change meanwhile
                due, previous = due + gap / self.rate, timestamp
                if connection.topic == EPISODE_TOPIC:
                    event = deserialize_message(bytes(raw), EpisodeEvent)
                    if event.event == EpisodeEvent.EVENT_STARTED:
                        if sent_ahead and event.episode == episode:
                            sent_ahead = False
                            continue          # sent ahead of its states already
                        if starts.get(event.episode):
                            starts[event.episode].popleft()
                        self.start_episode(events, bytes(raw))
                        episode, sent_ahead = event.episode, False
                        published += 1
                        continue
                elif connection.topic == STATES_TOPIC:
                    state_episode = deserialize_message(bytes(raw), VehicleStateArray).episode
                    if state_episode != episode:
                        queued = starts.get(state_episode)
                        from_bag = bool(queued)
                        self.start_episode(events, queued.popleft() if from_bag else serialize_message(EpisodeEvent(
                            episode=state_episode, event=EpisodeEvent.EVENT_STARTED, seed=-1)))
                        episode, sent_ahead = state_episode, from_bag
                publishers[connection.topic].publish(bytes(raw))
                published += 1
                self.executor_.spin_once(timeout_sec=0.0)   # parameter requests, also at full speed
        finally:
            reader.close()
        self.get_logger().info(f'played {published} messages from {self.path}')


def main() -> int:
    return run_node('player', Player, lambda node: node.play())


if __name__ == '__main__':
    raise SystemExit(main())
