"""Repair of an unfinished bag (a recorder killed with SIGKILL): rewritten from its complete chunks."""
from __future__ import annotations

import shutil
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from rosbags.rosbag2 import Writer

from exit_decision.ros.bags.storage import (BAG_ALLOWED, COMPRESSIONS, READ_ERRORS, BagError, first_line, open_writer,
                                            typestore)

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
