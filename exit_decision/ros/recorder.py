"""recorder: writes topics to a rosbag2 bag (mcap) with the rosbags library.

Subscriptions take the serialized CDR (raw) and store it unchanged, stamped with the receive
time as rosbag2 does. Ctrl-C or SIGTERM closes the bag properly: everything received is in
it and the bag is readable (only SIGKILL can leave an unfinished file). By default it records
the stack's topics (``bags.DEFAULT_TOPICS``), the visualizer's markers included, so a bag
opened in Foxglove or RViz shows the scene with no extra step.
"""
from __future__ import annotations

import time
from datetime import datetime
from pathlib import Path

from rclpy.node import Node
from rosbags.rosbag2 import StoragePlugin, Writer

from exit_decision.ros.bags import DEFAULT_TOPICS, KNOWN_TOPICS, message_class, topic_qos, typestore
from exit_decision.ros.common import RECORDER_QOS, Diagnostics, describe, run_node


class Recorder(Node):
    def __init__(self):
        super().__init__('recorder')
        default_path = f'bags/exit_decision_{datetime.now():%Y%m%d_%H%M%S}'
        self.path = Path(self.declare_parameter('bag_path', default_path, describe(
            'directory of the bag to write (must not exist)', read_only=True)).value)
        topics = list(self.declare_parameter('topics', list(DEFAULT_TOPICS), describe(
            'topics to record; types of others than the known ones are found on the ROS graph',
            read_only=True)).value)
        self.store = typestore()
        self.writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections = {}
        self.counts = dict.fromkeys(topics, 0)
        self.diagnostics = Diagnostics(self, 'recorder')
        self.waiting = [topic for topic in topics if not self.subscribe(topic, KNOWN_TOPICS.get(topic))]
        if self.waiting:
            self.discovery = self.create_timer(0.5, self.discover)
        self.get_logger().info(f'recording {", ".join(topics)} to {self.path}')

    def subscribe(self, topic: str, type_name: str | None) -> bool:
        if type_name is None:
            return False
        self.connections[topic] = self.writer.add_connection(topic, type_name, typestore=self.store)
        self.create_subscription(message_class(type_name), topic, lambda raw, t=topic: self.write(t, raw),
                                 topic_qos(topic, RECORDER_QOS), raw=True)
        return True

    def discover(self) -> None:
        found = dict(self.get_topic_names_and_types())
        for topic in list(self.waiting):
            if topic in found:
                self.subscribe(topic, found[topic][0])
                self.waiting.remove(topic)
        if not self.waiting:
            self.discovery.cancel()

    def write(self, topic: str, raw: bytes) -> None:
        self.writer.write(self.connections[topic], time.time_ns(), raw)
        self.counts[topic] += 1
        self.diagnostics.count('messages')

    def destroy_node(self) -> None:
        self.writer.close()
        summary = ', '.join(f'{topic}: {count}' for topic, count in self.counts.items())
        self.get_logger().info(f'bag closed: {self.path} ({summary})')
        super().destroy_node()


def main() -> int:
    return run_node('recorder', Recorder)


if __name__ == '__main__':
    raise SystemExit(main())
