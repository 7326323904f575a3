"""Vehicle states (``exit_decision_msgs/VehicleStateArray``) to and from their CDR bytes
directly, without rclpy's message objects.

The bridge publishes a states message every step, and the graph builder, the decision node
and the visualizer decode them. Through rclpy, a message of 20 vehicles cost the bridge about
0.23 ms to build and convert (``states_to_msg``, then the middleware's conversion in
``publish``) and a reader 0.25 ms to decode (``deserialize_message``, ``states_from_msg``);
here 0.04 ms and 0.07 ms (docs/design.md, "ROS 2 -> Speed"). The layout is the message's
plain CDR (``cdr``). Tests check both directions against rclpy's serialisation on an
episode's states;
``conversions.states_to_msg`` stays for who needs the message object.
"""
from __future__ import annotations

import math
import struct
from collections.abc import Collection, Sequence
from dataclasses import dataclass

from builtin_interfaces.msg import Time

from exit_decision.input_checks import StateLimits
from exit_decision.ros.messages.cdr import (EPISODE_STEP, LITTLE_ENDIAN, STAMP, UINT32, check_little_endian, finish,
                                            pad, string)
from exit_decision.ros.messages.conversions import (CLASS_CODES, CLASS_NAMES, MessageError, check_unique_ids,
                                                    check_vehicle_fields, stamp_of)
from exit_decision.traffic import VehicleState


@dataclass(frozen=True)
class DecodedStates:
    episode: int
    step: int
    step_length: float
    stamp: Time                     # the header's
    vehicles: list[VehicleState]


_LENGTH_COUNT = struct.Struct('<dI')
_CLASS_LANE = struct.Struct('<Bb')
_NUMBERS_INTENTION = struct.Struct('<6db')


def encode_states(vehicles: Sequence[VehicleState], *, episode: int, step: int, step_length: float,
                  frame_id: str = 'road') -> bytes:
    """The CDR bytes ``conversions.states_to_msg`` would give (stamp: the step's time), little endian."""
    stamp = stamp_of(step * step_length)
    out = bytearray(LITTLE_ENDIAN)
    out += STAMP.pack(stamp.sec, stamp.nanosec)
    out += string(frame_id)
    pad(out, 4)
    out += EPISODE_STEP.pack(episode, step)
    pad(out, 8)
    out += _LENGTH_COUNT.pack(step_length, len(vehicles))
    for v in vehicles:
        pad(out, 4)
        out += string(v.vehicle_id)
        out += _CLASS_LANE.pack(CLASS_CODES[v.vehicle_class], v.lane_index)
        pad(out, 4)
        out += string(v.edge_id)
        pad(out, 8)
        out += _NUMBERS_INTENTION.pack(v.position, v.lateral_offset, v.speed, v.acceleration, v.length,
                                          v.lane_speed_limit, v.intention)
        pad(out, 4)
        out += string(v.route_target)
        out += b'\x01' if v.controlled else b'\x00'
    return finish(out)


def decode_states(cdr: bytes, highway_edges: Collection[str]) -> DecodedStates:
    """The message's fields and its vehicles, as ``conversions.states_from_msg`` makes them from
    a message (``check_vehicle_fields``, ``check_unique_ids``); MessageError for bytes that
    are no such message."""
    try:
        return _decode(cdr, highway_edges)
    except (struct.error, IndexError, UnicodeDecodeError) as error:
        raise MessageError(f'vehicle states: not a VehicleStateArray in CDR ({error})') from None


def _decode(cdr: bytes, highway_edges: Collection[str]) -> DecodedStates:
    # offsets count from the start of the buffer; CDR aligns from the end of the 4-byte header
    check_little_endian(cdr, 'vehicle states')
    uint32, class_lane, numbers_intention = UINT32.unpack_from, _CLASS_LANE.unpack_from, _NUMBERS_INTENTION.unpack_from
    sec, nanosec = STAMP.unpack_from(cdr, 4)
    (size,) = uint32(cdr, 12)
    offset = 16 + size
    offset += -offset % 4
    episode, step = EPISODE_STEP.unpack_from(cdr, offset)
    offset += 8
    offset += -(offset - 4) % 8
    step_length, count = _LENGTH_COUNT.unpack_from(cdr, offset)
    offset += 12
    vehicles = []
    for _ in range(count):
        # each string: uint32 length n with the NUL, n bytes; the NUL's index kept to check it.
        # Inline on purpose: with a function per string and per alignment the decode took 119 us
        # a message instead of 67-71 (the same 801 states, back to back)
        offset += -offset % 4
        (size,) = uint32(cdr, offset)
        id_end = offset + 3 + size
        vehicle_id = cdr[offset + 4:id_end].decode()
        offset += 4 + size
        code, lane = class_lane(cdr, offset)
        offset += 2
        offset += -offset % 4
        (size,) = uint32(cdr, offset)
        edge_end = offset + 3 + size
        edge = cdr[offset + 4:edge_end].decode()
        offset += 4 + size
        offset += -(offset - 4) % 8
        *numbers, intention = numbers_intention(cdr, offset)
        offset += 49
        offset += -offset % 4
        (size,) = uint32(cdr, offset)
        route_end = offset + 3 + size
        route_target = cdr[offset + 4:route_end].decode()
        offset += 4 + size
        controlled = cdr[offset] != 0   # IndexError (so MessageError) if the bytes end before
        offset += 1
        if cdr[id_end] or cdr[edge_end] or cdr[route_end] or '\0' in vehicle_id + edge + route_target:
            raise MessageError(f'vehicle {vehicle_id!r}: a string that is not one NUL-terminated string')
        if code not in CLASS_NAMES or not vehicle_id or not all(map(math.isfinite, numbers)):
            check_vehicle_fields(vehicle_id, code, numbers)   # says which
        vehicles.append(VehicleState(vehicle_id, CLASS_NAMES[code], lane, edge, *numbers, intention, route_target,
                                     controlled, edge in highway_edges))
    check_unique_ids(vehicles)
    return DecodedStates(episode, step, step_length, Time(sec=sec, nanosec=nanosec), vehicles)


def checked_states_cdr(cdr: bytes, limits: StateLimits) -> DecodedStates:
    """The states message in ``cdr``, every field checked against the scenario (InputError
    naming the first that does not fit): what the graph builder, the decision node and the
    visualizer take."""
    states = decode_states(cdr, limits.highway_edges)
    limits.check(states.vehicles, step=states.step, step_length=states.step_length)
    return states
