"""The pieces of plain CDR (what rmw_fastrtps writes) that the message codecs of the decision
path share (``states_cdr``, ``commands_cdr``, ``events_cdr``): a 4-byte encapsulation header, then each field
aligned to its size (at most 8) from the end of that header, a string as a uint32 length
counting its NUL, its bytes, the NUL, the whole padded to 4 bytes. Little endian only: every
ROS 2 host here writes it, and the decoders refuse the other order.
"""
from __future__ import annotations

import struct

from exit_decision.ros.messages.conversions import MessageError

LITTLE_ENDIAN = b'\x00\x01\x00\x00'   # CDR_LE, no options
UINT32 = struct.Struct('<I')
STAMP = struct.Struct('<iI')          # builtin_interfaces/Time: int32 sec, uint32 nanosec
EPISODE_STEP = struct.Struct('<II')


def string(text: str) -> bytes:
    data = text.encode()
    return UINT32.pack(len(data) + 1) + data + b'\0'


def pad(out: bytearray, alignment: int) -> None:
    """Align the end of ``out`` (which starts with the encapsulation header) to ``alignment``."""
    out += b'\0' * (-(len(out) - 4) % alignment)


def aligned(offset: int, alignment: int) -> int:
    """``offset`` (from the message's first byte) moved up to ``alignment`` from the end of the
    encapsulation header: where a field read there begins (``pad``'s counterpart)."""
    return offset + -(offset - 4) % alignment


def finish(out: bytearray) -> bytes:
    """The message's bytes: ``out`` padded to 4."""
    out += b'\0' * (-len(out) % 4)
    return bytes(out)


def check_little_endian(cdr: bytes, what: str) -> None:
    if cdr[:2] != LITTLE_ENDIAN[:2]:
        raise MessageError(f'{what}: encapsulation {bytes(cdr[:2]).hex()} is not little-endian CDR '
                           f'({LITTLE_ENDIAN[:2].hex()}), what every ROS 2 host here writes')


def read_string(cdr: bytes, offset: int) -> tuple[str, int]:
    """The string at ``offset`` (aligned to 4 first) and the offset after it; MessageError for one
    that is not a single NUL-terminated string."""
    offset += -offset % 4
    (size,) = UINT32.unpack_from(cdr, offset)
    end = offset + 3 + size
    text = cdr[offset + 4:end].decode()
    if size == 0 or cdr[end] or '\0' in text:
        raise MessageError(f'{text!r}: a string that is not one NUL-terminated string')
    return text, offset + 4 + size
