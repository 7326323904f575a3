"""Gaps in recorded step sequences: which steps of an episode a recording is missing.

ROS-free: the recorder stores messages as the CDR bytes it received and reads only the
(episode, step) at the front of the stack's stamped messages (vehicle states, graph,
commands all start ``std_msgs/Header header, uint32 episode, uint32 step``), which costs
microseconds instead of a full deserialization.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

from exit_decision.input_checks import InputError


def episode_and_step(cdr: bytes) -> tuple[int, int]:
    """(episode, step) of a serialized message that starts with a Header, then uint32 episode
    and uint32 step. CDR: 4 bytes of encapsulation (byte 1: 1 little endian, 0 big endian),
    then stamp (int32 sec, uint32 nanosec), frame_id (uint32 length with the NUL, the bytes),
    padding to 4. InputError for bytes too short to hold them."""
    try:
        order = '<' if cdr[1] & 1 else '>'
        (length,) = struct.unpack_from(order + 'I', cdr, 12)
        offset = 4 + (8 + 4 + length + 3) // 4 * 4
        return struct.unpack_from(order + 'II', cdr, offset)
    except (IndexError, struct.error):
        raise InputError(f'{len(cdr)} bytes: too short for a header, an episode and a step') from None


@dataclass
class StepGaps:
    """Holes in one stream's steps within an episode: a message every ``stride`` steps is
    expected (1 for states, the decision interval for graphs and commands). A hole is counted
    between two messages of one episode; a stream's start and end are not (a recorder or node
    may join late, and a stream's last message races its episode's end)."""
    stride: int = 1
    episode: int | None = None
    last: int = 0       # newest step taken in the episode
    gaps: int = 0       # holes
    missing: int = 0    # steps in them

    def see(self, episode: int, step: int) -> int:
        """Take the message of (episode, step); the steps missing right before it (0 if none)."""
        if episode != self.episode:
            self.episode, self.last = episode, step
            return 0
        missing = max((step - self.last) // self.stride - 1, 0)
        self.last = max(step, self.last)
        if missing:
            self.gaps += 1
            self.missing += missing
        return missing
