"""player: republishes a bag's topics with their recorded timing (and so its /clock).

Messages go out serialized, exactly as recorded, ``rate`` times as fast as recorded.
"""
from __future__ import annotations

import time
from pathlib import Path

import rclpy
from rclpy.node import Node
from rosbags.rosbag2 import Reader

from exit_decision.ros.bags import message_class, topic_qos
from exit_decision.ros.common import describe, run_node


class Player(Node):
    def __init__(self):
        super().__init__('player')
        self.path = Path(self.declare_parameter('bag_path', '', describe('bag to play', read_only=True)).value)
        self.rate = self.declare_parameter('rate', 1.0, describe('playback speed factor',
                                                                 float_range=(0.01, 1000.0))).value
        self.wait_for_subscribers = self.declare_parameter('wait_for_subscribers', 0, describe(
            'before playing, wait (up to 30 s) until every topic has this many subscribers; 0: '
            'half a second for discovery', read_only=True, integer_range=(0, 100))).value
        if not self.path.exists():
            raise FileNotFoundError(f'{self.path}: no such bag')

    def play(self) -> None:
        published = 0
        with Reader(self.path) as reader:
            publishers = {c.topic: self.create_publisher(message_class(c.msgtype), c.topic, topic_qos(c.topic))
                          for c in reader.connections}
            deadline = time.monotonic() + (30.0 if self.wait_for_subscribers else 0.5)
            while time.monotonic() < deadline and (not self.wait_for_subscribers or any(
                    p.get_subscription_count() < self.wait_for_subscribers for p in publishers.values())):
                time.sleep(0.05)   # let subscribers match: a reliable volatile topic does not resend
            start_wall, start_bag = time.monotonic(), None
            for connection, timestamp, raw in reader.messages():
                if not rclpy.ok(context=self.context):
                    break
                start_bag = timestamp if start_bag is None else start_bag
                delay = (timestamp - start_bag) / 1e9 / self.rate - (time.monotonic() - start_wall)
                if delay > 0:
                    time.sleep(delay)
                publishers[connection.topic].publish(bytes(raw))
                published += 1
        self.get_logger().info(f'played {published} messages from {self.path}')


def main() -> int:
    return run_node('player', Player, lambda node: node.play())


if __name__ == '__main__':
    raise SystemExit(main())
