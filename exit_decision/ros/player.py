"""player: republishes a bag's topics with their recorded timing (and so its /clock).

Messages go out serialized, exactly as recorded, ``rate`` times as fast as recorded. The
nodes start an episode's sequence checks on its EVENT_STARTED, so the player sends each
episode's start before the episode's first states: the bag's own event, moved ahead if the
recorder wrote it after them, or one made here if the bag has none.

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
from rclpy.node import Node
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.rosbag2 import Reader, ReaderError

from exit_decision.ros.bags import message_class, topic_qos
from exit_decision.ros.common import (EPISODE_TOPIC, EVENT_QOS, STATES_TOPIC, ParameterError, declare, describe,
                                      run_node)

BAG_ALLOWED = 'a rosbag2 (mcap) directory, as the recorder writes'


def first_line(error: Exception) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0].rstrip(':')


class Player(Node):
    def __init__(self):
        super().__init__('player')
        self.path = Path(declare(self, 'bag_path', '', describe('bag to play', read_only=True,
                                                                 constraints=BAG_ALLOWED)))
        self.rate = declare(self, 'rate', 1.0, describe('playback speed factor', float_range=(0.01, 1000.0)))
        self.wait_for_subscribers = declare(self, 'wait_for_subscribers', 0, describe(
            'before playing, wait (up to 30 s) until every topic has this many subscribers; 0: '
            'half a second for discovery', read_only=True, integer_range=(0, 100)))
        if not str(self.path) or str(self.path) == '.':
            raise ParameterError(f'parameter bag_path: not given; allowed: {BAG_ALLOWED}')
        if not self.path.exists():
            raise ParameterError(f'parameter bag_path: {self.path}: no such bag; allowed: {BAG_ALLOWED}')
        self.reader().close()   # a bag that cannot be opened stops the node here, before anything is published

    def reader(self) -> Reader:
        """The bag, open."""
        try:
            reader = Reader(self.path)
            reader.open()
        except (ReaderError, OSError, ValueError, KeyError) as error:
            raise ParameterError(f'parameter bag_path: {self.path}: not a readable bag ({first_line(error)}); '
                                 f'allowed: {BAG_ALLOWED}') from None
        return reader

    def play(self) -> None:
        try:
            self._play()
        except (ReaderError, OSError, ValueError, KeyError, RuntimeError) as error:   # RuntimeError: bad CDR
            raise ParameterError(f'parameter bag_path: {self.path}: the bag is corrupt ({first_line(error)}); '
                                 f'allowed: {BAG_ALLOWED}') from None

    def _play(self) -> None:
        published = 0
        reader = self.reader()
        try:
            publishers = {c.topic: self.create_publisher(message_class(c.msgtype), c.topic, topic_qos(c.topic))
                          for c in reader.connections}
            events = publishers.get(EPISODE_TOPIC) or self.create_publisher(EpisodeEvent, EPISODE_TOPIC, EVENT_QOS)
            starts: dict[int, deque] = {}   # episode -> the bag's EVENT_STARTED messages, in order
            recorded_events = [c for c in reader.connections if c.topic == EPISODE_TOPIC]
            for _, _, raw in reader.messages(connections=recorded_events) if recorded_events else ():
                event = deserialize_message(bytes(raw), EpisodeEvent)
                if event.event == EpisodeEvent.EVENT_STARTED:
                    starts.setdefault(event.episode, deque()).append(bytes(raw))
            deadline = time.monotonic() + (30.0 if self.wait_for_subscribers else 0.5)
            while time.monotonic() < deadline and (not self.wait_for_subscribers or any(
                    p.get_subscription_count() < self.wait_for_subscribers for p in publishers.values())):
                time.sleep(0.05)   # let subscribers match: a reliable volatile topic does not resend
            episode, sent_ahead = None, False   # the episode started last; its bag event already sent
            start_wall, start_bag = time.monotonic(), None
            for connection, timestamp, raw in reader.messages():
                if not rclpy.ok(context=self.context):
                    break
                start_bag = timestamp if start_bag is None else start_bag
                delay = (timestamp - start_bag) / 1e9 / self.rate - (time.monotonic() - start_wall)
                if delay > 0:
                    time.sleep(delay)
                if connection.topic == EPISODE_TOPIC:
                    event = deserialize_message(bytes(raw), EpisodeEvent)
                    if event.event == EpisodeEvent.EVENT_STARTED:
                        if sent_ahead and event.episode == episode:
                            sent_ahead = False
                            continue          # sent ahead of its states already
                        if starts.get(event.episode):
                            starts[event.episode].popleft()
                        episode, sent_ahead = event.episode, False
                elif connection.topic == STATES_TOPIC:
                    state_episode = deserialize_message(bytes(raw), VehicleStateArray).episode
                    if state_episode != episode:
                        queued = starts.get(state_episode)
                        from_bag = bool(queued)
                        events.publish(queued.popleft() if from_bag else serialize_message(EpisodeEvent(
                            episode=state_episode, event=EpisodeEvent.EVENT_STARTED, seed=-1)))
                        events.wait_for_all_acked(Duration(seconds=1.0))
                        episode, sent_ahead = state_episode, from_bag
                publishers[connection.topic].publish(bytes(raw))
                published += 1
        finally:
            reader.close()
        self.get_logger().info(f'played {published} messages from {self.path}')


def main() -> int:
    return run_node('player', Player, lambda node: node.play())


if __name__ == '__main__':
    raise SystemExit(main())
