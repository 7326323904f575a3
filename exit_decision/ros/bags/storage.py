"""rosbag2 (mcap) files with the ``rosbags`` library: the type store, the topics, reading and writing.

Bags carry the custom message definitions (registered from the installed .msg files), so
``ros2 bag info`` / ``ros2 bag play`` on a Jazzy install can read them. Data is the CDR that
rclpy sends, stored as is.

A bag that cannot be read (missing, empty, corrupt, or unfinished: a recorder killed with
SIGKILL leaves an mcap file with no summary and no metadata.yaml) raises ``BagError``, one
line saying what is wrong and what to do. ``repair_bag`` (``bags/repair.py``) makes an unfinished
bag readable up to its last complete chunk and says what was lost.

Chunks are written zstd-compressed or not at all (``open_writer``, ``COMPRESSIONS``). Readers
need no option: each chunk names its compression; bags with the format's other compression,
lz4 (another recorder's), are read as well.
"""
from __future__ import annotations

import importlib
import struct
from collections.abc import Iterator
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from rclpy.qos import QoSProfile, qos_profile_parameter_events
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, ReaderError, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from exit_decision.ros.topics import (CLOCK_QOS, CLOCK_TOPIC, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC,
                                      EVENT_QOS, GRAPH_TOPIC, MARKERS_TOPIC, OPTIONS_TOPIC, OVERRIDES_TOPIC,
                                      STATES_TOPIC, STREAM_QOS)

#: what the recorder records by default, with the types
DEFAULT_TOPICS = {
    STATES_TOPIC: 'exit_decision_msgs/msg/VehicleStateArray',
    GRAPH_TOPIC: 'exit_decision_msgs/msg/TrafficGraph',
    COMMANDS_TOPIC: 'exit_decision_msgs/msg/CavCommandArray',
    EPISODE_TOPIC: 'exit_decision_msgs/msg/EpisodeEvent',
    OVERRIDES_TOPIC: 'exit_decision_msgs/msg/ShieldOverrideArray',   # the CAVs the shield overrode, per decision
    OPTIONS_TOPIC: 'exit_decision_msgs/msg/CavOptionArray',   # the options policy CAVs hold, per decision
    CLOCK_TOPIC: 'rosgraph_msgs/msg/Clock',
    '/parameter_events': 'rcl_interfaces/msg/ParameterEvent',
    MARKERS_TOPIC: 'visualization_msgs/msg/MarkerArray',   # the visualizer's scene: a bag opens in Foxglove/RViz
}
KNOWN_TOPICS = {**DEFAULT_TOPICS, DIAGNOSTICS_TOPIC: 'diagnostic_msgs/msg/DiagnosticArray'}
#: what a bag argument must be, for error messages
BAG_ALLOWED = 'a rosbag2 (mcap) directory, as the recorder writes'
#: errors rosbags and rclpy raise on a bag whose files are damaged (RuntimeError: CDR rclpy cannot read)
READ_ERRORS = (ReaderError, OSError, ValueError, KeyError, EOFError, struct.error, RuntimeError)
#: mcap chunk compressions a bag is written with: zstd, which rosbags' writer offers and rosbag2's
#: mcap presets use (lz4, the format's other one, would take rosbags' internals and an extra
#: dependency for a bag 1.5x zstd's: recorder.py), or none
COMPRESSIONS = ('none', 'zstd')


class BagError(ValueError):
    """A bag that cannot be read; the text names the bag, what is wrong and what to do."""


def first_line(error: Exception) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0].rstrip(':')


def topic_qos(topic: str, default: QoSProfile = STREAM_QOS) -> QoSProfile:
    """The QoS the stack's publishers offer on a topic (subscribers must be compatible)."""
    return {CLOCK_TOPIC: CLOCK_QOS, EPISODE_TOPIC: EVENT_QOS, MARKERS_TOPIC: STREAM_QOS,   # the visualizer's
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


def open_writer(path: Path, compression: str = 'none') -> Writer:
    """A new mcap bag at ``path``, open, its chunks compressed with ``compression`` (one of
    COMPRESSIONS): zstd is rosbags' CompressionMode.STORAGE (its metadata then names no file or
    message compression, as rosbag2's does for chunk compression)."""
    if compression not in COMPRESSIONS:
        raise ValueError(f'compression {compression!r}; allowed: {" | ".join(COMPRESSIONS)}')
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compression == 'zstd':
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    return writer


def open_bag(path: Path) -> Reader:
    """The bag at ``path``, open; BagError if it is missing, empty, unfinished or corrupt."""
    if not str(path) or str(path) == '.':
        raise BagError(f'not given; allowed: {BAG_ALLOWED}')
    if not path.exists():
        raise BagError(f'{path}: no such bag; allowed: {BAG_ALLOWED}')
    if path.is_dir() and not (path / 'metadata.yaml').exists():
        if list(path.glob('*.mcap')):
            raise BagError(f'{path}: unfinished bag (no metadata.yaml: the recorder did not close it); '
                           f'`exit-decision bag repair {path}` recovers it up to its last complete chunk')
        raise BagError(f'{path}: {"empty directory" if not any(path.iterdir()) else "no metadata.yaml"}, '
                       f'not a bag; allowed: {BAG_ALLOWED}')
    try:
        reader = Reader(path)
        reader.open()
    except READ_ERRORS as error:
        raise BagError(f'{path}: not a readable bag ({first_line(error)}); allowed: {BAG_ALLOWED}') from None
    return reader


def read_messages(path: Path, topics: set[str] | None = None) -> Iterator[tuple[str, str, int, object]]:
    """(topic, type, timestamp [ns], rclpy message) in bag order; BagError if the bag cannot be read."""
    classes: dict[str, type] = {}
    reader = open_bag(path)
    try:
        connections = [c for c in reader.connections if topics is None or c.topic in topics]
        for connection, timestamp, raw in reader.messages(connections=connections):
            cls = classes.setdefault(connection.msgtype, message_class(connection.msgtype))
            yield connection.topic, connection.msgtype, timestamp, deserialize_message(bytes(raw), cls)
    except READ_ERRORS as error:
        raise BagError(f'{path}: the bag is corrupt ({first_line(error)})') from None
    finally:
        reader.close()
