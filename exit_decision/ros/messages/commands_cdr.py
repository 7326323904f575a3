"""CAV commands (``exit_decision_msgs/CavCommandArray``) to and from their CDR bytes directly,
without rclpy's message objects: the decision node publishes them and the bridge decodes them
while it waits on a decision step, so both are on the way from states to commands.

Through rclpy a message of 7 commands cost the decision node 33 us to build and convert
(``conversions.commands_to_msg``, then ``serialize``) and the bridge 47 us to decode
(``deserialize``, then ``conversions.commands_from_msg``), measured alone; inside the stack,
on a core that the simulation shares, about twice that. The layout is plain CDR (``cdr``);
tests check both directions against rclpy's serialisation.
"""
from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass

from builtin_interfaces.msg import Time

from exit_decision.ros.messages.cdr import (EPISODE_STEP, LITTLE_ENDIAN, STAMP, UINT32, check_little_endian, finish,
                                            pad, read_string, string)
from exit_decision.ros.messages.conversions import MessageError, check_vehicle_entry
from exit_decision.traffic import CavCommand

_LANE_CHANGE = struct.Struct('<b')
_ACCELERATION = struct.Struct('<f')


@dataclass(frozen=True)
class DecodedCommands:
    episode: int
    step: int
    stamp: Time                          # the header's
    mode: str
    algorithm: str
    policy: str
    commands: dict[str, CavCommand]      # vehicle id -> command, as ``conversions.commands_from_msg``


def encode_commands(commands: Mapping[str, CavCommand], *, episode: int, step: int, stamp: Time,
                    mode: str, algorithm: str, policy: str) -> bytes:
    """The CDR bytes of ``conversions.commands_to_msg`` (frame ``road``), little endian."""
    out = bytearray(LITTLE_ENDIAN)
    out += STAMP.pack(stamp.sec, stamp.nanosec)
    out += string('road')
    pad(out, 4)
    out += EPISODE_STEP.pack(episode, step)
    for text in (mode, algorithm, policy):
        pad(out, 4)
        out += string(text)
    pad(out, 4)
    out += UINT32.pack(len(commands))
    for vehicle_id, command in commands.items():
        pad(out, 4)
        out += string(vehicle_id)
        out += _LANE_CHANGE.pack(command.lane_change)
        pad(out, 4)
        out += _ACCELERATION.pack(command.acceleration)
    return finish(out)


def decode_commands(cdr: bytes) -> DecodedCommands:
    """The message's fields and its commands; MessageError for bytes that are no such message,
    a vehicle listed twice or an acceleration that is not finite (as ``commands_from_msg``)."""
    try:
        check_little_endian(cdr, 'commands')
        sec, nanosec = STAMP.unpack_from(cdr, 4)
        _, offset = read_string(cdr, 12)
        offset += -offset % 4
        episode, step = EPISODE_STEP.unpack_from(cdr, offset)
        mode, offset = read_string(cdr, offset + 8)
        algorithm, offset = read_string(cdr, offset)
        policy, offset = read_string(cdr, offset)
        offset += -offset % 4
        (count,) = UINT32.unpack_from(cdr, offset)
        offset += 4
        commands = {}
        for _ in range(count):
            vehicle_id, offset = read_string(cdr, offset)
            (lane_change,) = _LANE_CHANGE.unpack_from(cdr, offset)
            offset += 1
            offset += -offset % 4
            (acceleration,) = _ACCELERATION.unpack_from(cdr, offset)
            offset += 4
            check_vehicle_entry(vehicle_id, (acceleration,), commands, 'commands')
            commands[vehicle_id] = CavCommand(lane_change, acceleration)
    except (struct.error, IndexError, UnicodeDecodeError) as error:
        raise MessageError(f'commands: not a CavCommandArray in CDR ({error})') from None
    return DecodedCommands(episode, step, Time(sec=sec, nanosec=nanosec), mode, algorithm, policy, commands)
