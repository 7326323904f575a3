"""Taking serialized messages with the id of their publisher (rcl's ``rcl_take_serialized_message``),
and dropping those a node would refuse unread before they reach Python (``_drain.c``).

rclpy's take gives a message's info without the publisher's gid (Jazzy's dict holds the two
timestamps and the two sequence numbers only), so with several publishers on a topic a node
could not tell whose sequence a number belongs to, and the messages a full queue overwrote
went uncounted. rcl's own take fills the whole ``rmw_message_info_t``, gid included. This module
finds it through ctypes on the libraries rclpy has loaded already, and ``_drain.c`` calls it in
a loop on the subscription rclpy made (its ``handle.pointer``), into the structures here, which
mirror rmw/types.h and rcutils/types/uint8_array.h of Jazzy (``RMW_GID_STORAGE_SIZE`` 16); a test
takes through it and checks each field against rclpy's own take.
"""
from __future__ import annotations

import ctypes
import importlib
import struct

from exit_decision.ros import _drain

RCL_RET_OK = 0
RMW_GID_STORAGE_SIZE = 16
INITIAL_CAPACITY = 4096   # [bytes] the middleware grows the buffer to a larger message


class _Allocator(ctypes.Structure):
    _fields_ = [('allocate', ctypes.c_void_p), ('deallocate', ctypes.c_void_p), ('reallocate', ctypes.c_void_p),
                ('zero_allocate', ctypes.c_void_p), ('state', ctypes.c_void_p)]


class _SerializedMessage(ctypes.Structure):   # rcutils_uint8_array_t
    _fields_ = [('buffer', ctypes.POINTER(ctypes.c_uint8)), ('buffer_length', ctypes.c_size_t),
                ('buffer_capacity', ctypes.c_size_t), ('allocator', _Allocator)]


class _Gid(ctypes.Structure):
    _fields_ = [('implementation_identifier', ctypes.c_char_p), ('data', ctypes.c_uint8 * RMW_GID_STORAGE_SIZE)]


class _MessageInfo(ctypes.Structure):
    _fields_ = [('source_timestamp', ctypes.c_int64), ('received_timestamp', ctypes.c_int64),
                ('publication_sequence_number', ctypes.c_uint64), ('reception_sequence_number', ctypes.c_uint64),
                ('publisher_gid', _Gid), ('from_intra_process', ctypes.c_bool)]


_libraries: tuple | None = None


def _load() -> tuple:
    """rcl and rcutils as rclpy loaded them (dlopen by soname finds the loaded ones)."""
    global _libraries
    if _libraries is None:
        importlib.import_module('rclpy.impl.implementation_singleton')   # loads rcl and rcutils
        rcutils, rcl = ctypes.CDLL('librcutils.so'), ctypes.CDLL('librcl.so')
        rcutils.rcutils_get_default_allocator.restype = _Allocator
        rcutils.rcutils_uint8_array_init.argtypes = [ctypes.POINTER(_SerializedMessage), ctypes.c_size_t,
                                                     ctypes.POINTER(_Allocator)]
        rcutils.rcutils_uint8_array_init.restype = ctypes.c_int
        _libraries = rcutils, rcl
    return _libraries


#: what ``drain`` stopped at, and why it dropped a message: ``_drain.c``'s own values
QUEUE_EMPTY, MESSAGE_WAITING, MORE_MAY_WAIT = _drain.QUEUE_EMPTY, _drain.MESSAGE_WAITING, _drain.MORE_MAY_WAIT
TOO_LARGE, OUT_OF_WINDOW = _drain.TOO_LARGE, _drain.OUT_OF_WINDOW
#: a record of a message ``_drain.c`` dropped: publisher gid, sequence number, cause, then its
#: length (TOO_LARGE) or its episode and step (OUT_OF_WINDOW)
RECORD = struct.Struct('<16sQBII')
if RECORD.size != _drain.RECORD_BYTES:
    raise ImportError(f'exit_decision.ros._drain writes {_drain.RECORD_BYTES}-byte records, take.py reads '
                      f'{RECORD.size}: rebuild it (scripts/bootstrap.sh, or colcon build)')
RECORDS = 256            # dropped messages a drain call records at most
NO_LIMIT = 2 ** 64 - 1   # [bytes] a subscription outside the intake: every message reaches Python
LAST_STEP = 2 ** 32 - 1  # the largest step a header holds (uint32): a window up to it takes any step


class Bounds:
    """What a subscription lets through to Python (``SerializedTake.drain``): here, every message;
    ``intake.Bounded`` sets a size limit and a window of steps, and counts what they drop."""

    size_limit = NO_LIMIT

    def window(self) -> tuple[int, int, int] | None:
        """(episode, first step, last step) of the messages the subscriber can take now; None: any."""
        return None

    def dropped(self, records, count: int) -> None:
        """Count the ``count`` messages ``drain`` dropped (``SerializedTake.records``): none here."""


UNBOUNDED = Bounds()


class SerializedTake:
    """Takes the serialized messages of rclpy subscriptions with their publisher's gid, in C
    (``_drain.c``): those a subscription's bounds refuse (over its size limit, outside its step
    window) are dropped there and recorded; the others wait, one at a time, in one buffer (kept
    and grown by the middleware) until ``waiting`` copies them out."""

    def __init__(self):
        rcutils, rcl = _load()
        self._allocator = rcutils.rcutils_get_default_allocator()
        self._message, self._info = _SerializedMessage(), _MessageInfo()
        if rcutils.rcutils_uint8_array_init(ctypes.byref(self._message), INITIAL_CAPACITY,
                                            ctypes.byref(self._allocator)) != RCL_RET_OK:
            raise MemoryError('rcutils could not allocate a serialized message buffer')
        self._addresses = (ctypes.cast(rcl.rcl_take_serialized_message, ctypes.c_void_p).value,
                           ctypes.addressof(self._message), ctypes.addressof(self._info))
        self._records = bytearray(RECORD.size * RECORDS)

    def drain(self, subscription, size_limit: int = NO_LIMIT, window: tuple[int, int, int] | None = None,
              most: int = 0) -> tuple[int, int]:
        """Take messages of ``subscription`` (the caller holds its handle) until one is within
        ``size_limit`` and inside ``window`` ((episode, first step, last step); its header read
        where it has one), the queue is empty (``QUEUE_EMPTY``) or ``RECORDS`` dropped or ``most``
        (0: no limit) taken (``MORE_MAY_WAIT``): that status, and how many were dropped
        (``records``). After ``MESSAGE_WAITING`` the message is ``waiting``."""
        take, message, info = self._addresses
        episode, first, last = window or (-1, 0, 0)
        return _drain.drain(take, subscription.handle.pointer, message, info, size_limit, episode, first, last,
                     self._records, most)

    def records(self, count: int):
        """(gid, sequence number, cause, length or episode, 0 or step) of the ``count`` messages
        the last ``drain`` dropped."""
        return RECORD.iter_unpack(memoryview(self._records)[:count * RECORD.size])

    def waiting(self) -> tuple[bytes, dict]:
        """The message a ``drain`` left waiting, copied, and its info (rclpy's keys and
        ``publisher_gid``, 16 bytes)."""
        message, info = self._message, self._info
        return ctypes.string_at(message.buffer, message.buffer_length), {
            'source_timestamp': info.source_timestamp, 'received_timestamp': info.received_timestamp,
            'publication_sequence_number': info.publication_sequence_number,
            'reception_sequence_number': info.reception_sequence_number,
            'publisher_gid': bytes(info.publisher_gid.data)}
