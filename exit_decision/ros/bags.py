"""rosbag2 (mcap) files with the ``rosbags`` library: the type store, topics, reading, repair.

Bags carry the custom message definitions (registered from the installed .msg files), so
``ros2 bag info`` / ``ros2 bag play`` on a Jazzy install can read them. Data is the CDR that
rclpy sends, stored as is.

A bag that cannot be read (missing, empty, corrupt, or unfinished: a recorder killed with
SIGKILL leaves an mcap file with no summary and no metadata.yaml) raises ``BagError``, one
line saying what is wrong and what to do. ``repair_bag`` makes an unfinished bag readable up
to its last complete chunk and says what was lost.

Chunks are written zstd-compressed or not at all (``open_writer``, ``COMPRESSIONS``). Readers
need no option: each chunk names its compression; bags with the format's other compression,
lz4 (another recorder's), are read as well.
"""
from __future__ import annotations

import importlib
import shutil
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from rclpy.qos import QoSProfile, qos_profile_parameter_events
from rclpy.serialization import deserialize_message
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, ReaderError, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from exit_decision.ros.common import (CLOCK_QOS, CLOCK_TOPIC, COMMANDS_TOPIC, DIAGNOSTICS_TOPIC, EPISODE_TOPIC,
                                      EVENT_QOS, GRAPH_TOPIC, MARKERS_TOPIC, OVERRIDES_TOPIC, STATES_TOPIC,
                                      STREAM_QOS)

#: what the recorder records by default, with the types
DEFAULT_TOPICS = {
    STATES_TOPIC: 'exit_decision_msgs/msg/VehicleStateArray',
    GRAPH_TOPIC: 'exit_decision_msgs/msg/TrafficGraph',
    COMMANDS_TOPIC: 'exit_decision_msgs/msg/CavCommandArray',
    EPISODE_TOPIC: 'exit_decision_msgs/msg/EpisodeEvent',
    OVERRIDES_TOPIC: 'exit_decision_msgs/msg/ShieldOverrideArray',   # the CAVs the shield overrode, per decision
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


# --- repair ----------------------------------------------------------------------------------

MCAP_MAGIC = b'\x89MCAP0\r\n'
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_FOOTER, OP_DATA_END = 0x03, 0x04, 0x05, 0x06, 0x02, 0x0F


@dataclass
class RepairReport:
    """What ``repair_bag`` recovered and what was lost."""
    path: Path
    messages: dict[str, int] = field(default_factory=dict)   # topic -> messages recovered
    last_time: int = 0            # [ns] receive time of the last message recovered
    lost_bytes: int = 0           # bytes of the file after the last complete record (an unfinished chunk)
    unknown_types: list[str] = field(default_factory=list)   # topics whose messages were dropped
    kept: Path | None = None      # the unfinished file, kept beside the repaired one

    def summary(self) -> str:
        counts = ', '.join(f'{topic}: {n}' for topic, n in sorted(self.messages.items())) or 'none'
        until = datetime.fromtimestamp(self.last_time / 1e9).isoformat(sep=' ', timespec='milliseconds')
        cut = f'the last {self.lost_bytes} bytes of the file (an unfinished chunk) and ' if self.lost_bytes else ''
        lines = [(f'{self.path}: recovered {sum(self.messages.values())} messages received up to {until}, the '
                  f'last complete chunk ({counts})'),
                 (f'lost: what the recorder received after that: {cut}what it still held in memory (at most about '
                  f'a second of recording)')]
        if self.unknown_types:
            lines.append(f'also lost (types unknown here): {", ".join(self.unknown_types)}')
        lines.append(f'the unfinished file is kept as {self.kept}')
        return '\n'.join(lines)


def _string(body: bytes, offset: int) -> tuple[str, int]:
    (size,) = struct.unpack_from('<I', body, offset)
    return body[offset + 4:offset + 4 + size].decode(), offset + 4 + size


def _records(data: bytes) -> Iterator[tuple[int, bytes]]:
    """(opcode, body) of the mcap records in ``data`` (the records of a chunk)."""
    offset = 0
    while offset + 9 <= len(data):
        op, size = struct.unpack_from('<BQ', data, offset)
        yield op, data[offset + 9:offset + 9 + size]
        offset += 9 + size


def _complete_records(stream) -> Iterator[tuple[int, bytes]]:
    """(opcode, body) of the top-level records of an mcap file, up to the first one cut short."""
    while len(head := stream.read(9)) == 9:
        op, size = struct.unpack('<BQ', head)
        body = stream.read(size)
        if len(body) < size:
            return
        yield op, body


def repair_bag(path: Path) -> RepairReport:
    """Rewrite an unfinished bag (recorder killed) from its complete chunks, in place.

    The unfinished mcap file is kept beside the new one as ``<name>.mcap.unfinished``; the
    bag gets a new mcap file with its summary and a metadata.yaml, its chunks compressed as
    the first chunk of the old one was (zstd if that was lz4). BagError if the bag is no
    unfinished bag (missing, finished already, not an mcap file)."""
    from rosbags.rosbag2.storage_mcap import decompress, get_qos   # rosbags' own chunk check and QoS reader

    if not path.is_dir():
        raise BagError(f'{path}: no such bag directory; allowed: {BAG_ALLOWED}')
    files = sorted(path.glob('*.mcap'))
    if (path / 'metadata.yaml').exists():
        raise BagError(f'{path}: the bag is finished (it has its metadata.yaml); nothing to repair')
    if len(files) != 1:
        raise BagError(f'{path}: {len(files)} mcap files; allowed: a bag directory with the one mcap file the '
                       f'recorder writes')
    store = typestore()
    report = RepairReport(path)
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str, bytes]] = {}    # id -> topic, type, metadata
    staging = path.parent / f'.{path.name}.repair'
    shutil.rmtree(staging, ignore_errors=True)
    writer: Writer | None = None   # opened at the first chunk, with its compression
    connections: dict[int, object] = {}
    kept = 0
    try:
        with files[0].open('rb') as stream:
            if stream.read(8) != MCAP_MAGIC:
                raise BagError(f'{path}: {files[0].name} is not an mcap file; allowed: {BAG_ALLOWED}')

            def take(op: int, body: bytes) -> None:
                nonlocal writer
                if op == OP_SCHEMA:
                    (key,) = struct.unpack_from('<H', body)
                    schemas[key] = _string(body, 2)[0]
                elif op == OP_CHANNEL:
                    key, schema = struct.unpack_from('<HH', body)
                    topic, offset = _string(body, 4)
                    offset = _string(body, offset)[1]
                    (size,) = struct.unpack_from('<I', body, offset)
                    channels[key] = (topic, schemas.get(schema, ''), body[offset + 4:offset + 4 + size])
                elif op == OP_MESSAGE:
                    key, _, log_time = struct.unpack_from('<HIQ', body)
                    topic, msgtype, metadata = channels[key]
                    if writer is None:   # a message outside any chunk (not rosbags' way)
                        writer = open_writer(staging / path.name)
                    if key not in connections:
                        if msgtype not in store.types:
                            report.unknown_types.append(topic)
                            connections[key] = None
                        else:
                            connections[key] = writer.add_connection(
                                topic, msgtype, typestore=store, offered_qos_profiles=get_qos(metadata))
                    if connections[key] is not None:
                        writer.write(connections[key], log_time, body[22:])
                        report.messages[topic] = report.messages.get(topic, 0) + 1
                        report.last_time = max(report.last_time, log_time)

            for op, body in _complete_records(stream):
                if op in (OP_FOOTER, OP_DATA_END):
                    raise BagError(f'{path}: {files[0].name} is a finished mcap file (only its metadata.yaml is '
                                   f'missing); nothing to repair')
                if op == OP_CHUNK:
                    _, _, size, crc = struct.unpack_from('<QQQI', body)
                    compression, offset = _string(body, 28)
                    (length,) = struct.unpack_from('<Q', body, offset)
                    if writer is None:
                        kept_as = compression or 'none'
                        writer = open_writer(staging / path.name, kept_as if kept_as in COMPRESSIONS else 'zstd')
                    for record in _records(decompress(body[offset + 8:offset + 8 + length], compression, size, crc)):
                        take(*record)
                else:
                    take(op, body)
                kept = stream.tell()
            report.lost_bytes = stream.seek(0, 2) - kept
        if writer is None:   # not one complete chunk: an empty bag
            writer = open_writer(staging / path.name)
        writer.close()
    except BaseException as error:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(error, READ_ERRORS) and not isinstance(error, BagError):
            raise BagError(f'{path}: cannot repair it ({first_line(error)})') from None
        raise
    report.kept = files[0].with_name(files[0].name + '.unfinished')
    files[0].rename(report.kept)
    for written in (staging / path.name).iterdir():
        written.rename(path / written.name)
    shutil.rmtree(staging)
    return report
