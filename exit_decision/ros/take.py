"""Taking a serialized message with the id of its publisher (rcl's ``rcl_take_serialized_message``).

rclpy's take gives a message's info without the publisher's gid (Jazzy's dict holds the two
timestamps and the two sequence numbers only), so with several publishers on a topic a node
could not tell whose sequence a number belongs to, and the messages a full queue overwrote
went uncounted. rcl's own take fills the whole ``rmw_message_info_t``, gid included; this module
calls it through ctypes on the subscription rclpy made (its ``handle.pointer``), on the libraries
rclpy has loaded already. The structures mirror rmw/types.h and rcutils/types/uint8_array.h of
Jazzy (``RMW_GID_STORAGE_SIZE`` 16); a test takes through it and checks each field against
rclpy's own take.
"""
from __future__ import annotations

import ctypes
import importlib

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
        rcl.rcl_take_serialized_message.argtypes = [ctypes.c_void_p, ctypes.POINTER(_SerializedMessage),
                                                    ctypes.POINTER(_MessageInfo), ctypes.c_void_p]
        rcl.rcl_take_serialized_message.restype = ctypes.c_int32
        _libraries = rcutils, rcl
    return _libraries


class Unread:
    """A message taken over its size limit and not copied out of the middleware's buffer: its
    length (``len``) is all that is known of it."""

    __slots__ = ('length',)

    def __init__(self, length: int):
        self.length = length

    def __len__(self) -> int:
        return self.length


class SerializedTake:
    """Takes the serialized messages of rclpy subscriptions with their publisher's gid; one
    buffer, kept and grown by the middleware, copied into ``bytes`` per message within its
    size limit."""

    def __init__(self):
        rcutils, self._rcl = _load()
        self._allocator = rcutils.rcutils_get_default_allocator()
        self._message, self._info = _SerializedMessage(), _MessageInfo()
        if rcutils.rcutils_uint8_array_init(ctypes.byref(self._message), INITIAL_CAPACITY,
                                            ctypes.byref(self._allocator)) != RCL_RET_OK:
            raise MemoryError('rcutils could not allocate a serialized message buffer')
        # made once: a flood costs every message a take, and an empty queue one more
        self._take = self._rcl.rcl_take_serialized_message
        self._message_ref, self._info_ref = ctypes.byref(self._message), ctypes.byref(self._info)

    def __call__(self, subscription, size_limit: int | None = None) -> tuple[bytes | Unread, dict] | None:
        """The next message waiting on ``subscription`` (the caller holds its handle) and its info
        (rclpy's keys and ``publisher_gid``, 16 bytes), or None when none waits. A message over
        ``size_limit`` bytes is an ``Unread``: a flood of large ones costs no copy of each."""
        if self._take(subscription.handle.pointer, self._message_ref, self._info_ref, None) != RCL_RET_OK:
            return None
        message, info = self._message, self._info
        length = message.buffer_length
        data = Unread(length) if size_limit is not None and length > size_limit else \
            ctypes.string_at(message.buffer, length)
        return data, {
            'source_timestamp': info.source_timestamp, 'received_timestamp': info.received_timestamp,
            'publication_sequence_number': info.publication_sequence_number,
            'reception_sequence_number': info.reception_sequence_number,
            'publisher_gid': bytes(info.publisher_gid.data)}
