"""Episode events (``exit_decision_msgs/EpisodeEvent``): the episode and the event read from their
CDR bytes directly, for the nodes on the decision path, which use nothing else of them.

The graph builder takes every message on the topic to learn an episode's start, so a flood of
events costs it each one's reading: here two fields, checked in place, instead of rclpy's whole
message (``deserialize_message``; ``bench flood`` shows what the intake costs). The layout is fixed after
the header's frame id (plain CDR, ``cdr``; 8-byte fields aligned to 8 from the end of the
encapsulation), so every field's place is checked: bytes too short for the message, or longer
than it and its padding, are refused. Tests check it against rclpy's serialisation.
"""
from __future__ import annotations

import struct

from exit_decision.ros.messages.cdr import aligned, check_little_endian, read_string
from exit_decision.ros.messages.conversions import MessageError

_EPISODE = struct.Struct('<I')
#: from ``seed`` on (aligned to 8) every field's place is fixed: seed, event, truncated, (padding to
#: 4) steps, v_avs, v_s, p_collision, p_collision_cav, n_braking, braking_steps, p_cav, p_hv2, reward
_TAIL = struct.Struct('<qBB2xI4dII3d')


def decode_event(cdr: bytes) -> tuple[int, int]:
    """(episode, event) of an EpisodeEvent's CDR bytes; MessageError for bytes that are no such
    message (the wrong byte order, a bad frame id, too short, or longer than the message and
    its padding to 4)."""
    try:
        check_little_endian(cdr, 'episode event')
        _, offset = read_string(cdr, 12)
        offset = aligned(offset, 4)
        (episode,) = _EPISODE.unpack_from(cdr, offset)
        offset = aligned(offset + _EPISODE.size, 8)
        event = _TAIL.unpack_from(cdr, offset)[1]
        end = offset + _TAIL.size
    except (struct.error, IndexError, UnicodeDecodeError) as error:
        raise MessageError(f'episode event: not an EpisodeEvent in CDR ({error})') from None
    if len(cdr) > end + -end % 4:
        raise MessageError(f'episode event: {len(cdr)} bytes, more than an EpisodeEvent\'s {end}')
    return episode, event
