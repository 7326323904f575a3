"""rosbag2 (mcap) files with the ``rosbags`` library: the type store, topics, reading.

Bags carry the custom message definitions (registered from the installed .msg files), so
``ros2 bag info`` / ``ros2 bag play`` on a Jazzy install can read them. Data is the CDR that
rclpy sends, stored as is.
"""
from __future__ import annotations

import importlib
from collections.abc import Iterator
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from rclpy.qos import QoSProfile, qos_profile_parameter_events
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from exit_decision.ros.common import (CLOCK_QOS, CLOCK_TOPIC, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC,
                                      EVENT_QOS, GRAPH_TOPIC, MARKERS_TOPIC, STATES_TOPIC, STREAM_QOS)

#: what the recorder records by default, with the types
DEFAULT_TOPICS = {
    STATES_TOPIC: 'exit_decision_msgs/msg/VehicleStateArray',
    GRAPH_TOPIC: 'exit_decision_msgs/msg/TrafficGraph',
    COMMANDS_TOPIC: 'exit_decision_msgs/msg/CavCommandArray',
    EPISODE_TOPIC: 'exit_decision_msgs/msg/EpisodeEvent',
    CLOCK_TOPIC: 'rosgraph_msgs/msg/Clock',
    '/parameter_events': 'rcl_interfaces/msg/ParameterEvent',
    MARKERS_TOPIC: 'visualization_msgs/msg/MarkerArray',   # the visualizer's scene: a bag opens in Foxglove/RViz
}
KNOWN_TOPICS = {**DEFAULT_TOPICS, DIAGNOSTICS_TOPIC: 'diagnostic_msgs/msg/DiagnosticArray'}


def topic_qos(topic: str, default: QoSProfile = STREAM_QOS) -> QoSProfile:
    """The QoS the stack's publishers offer on a topic (subscribers must be compatible)."""
    return {CLOCK_TOPIC: CLOCK_QOS, EPISODE_TOPIC: EVENT_QOS,
            '/parameter_events': qos_profile_parameter_events}.get(topic, default)


def message_class(type_name: str) -> type:
    """'pkg/msg/Name' -> the rclpy message class."""
    package, _, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.msg'), name)


def typestore() -> Typestore:
    """ROS 2 Jazzy types plus exit_decision_msgs from the installed .msg files."""
    store = get_typestore(Stores.ROS2_JAZZY)
    share = Path(get_package_share_directory('exit_decision_msgs')) / 'msg'
    types = {}
    for path in sorted(share.glob('*.msg')):
        types.update(get_types_from_msg(path.read_text(), f'exit_decision_msgs/msg/{path.stem}'))
    store.register(types)
    return store


def read_messages(path: Path, topics: set[str] | None = None) -> Iterator[tuple[str, str, int, object]]:
    """(topic, type, timestamp [ns], rclpy message) in bag order."""
    classes: dict[str, type] = {}
    with Reader(path) as reader:
        connections = [c for c in reader.connections if topics is None or c.topic in topics]
        for connection, timestamp, raw in reader.messages(connections=connections):
            cls = classes.setdefault(connection.msgtype, message_class(connection.msgtype))
            yield connection.topic, connection.msgtype, timestamp, deserialize_message(bytes(raw), cls)
