"""sensor_msgs/JointState as CDR bytes, for `Publisher.publish(bytes)` (rclpy's publish_raw).

Why by hand, when rclpy serializes messages itself: joint_states is the one message a node sends
every poll period, from the bus owner thread whose caches are cold after each sleep. There,
rclpy's message path (the Python object converted to C, then serialized by the rmw) cost
350-360 us per 8-joint message against 250-260 us for these bytes published raw (50 Hz, a
subscriber in another process; `scripts/bench_command_path.py --part cpu` for the node's
share): at 50 Hz half a percent of a core, a third of what the CPU goal leaves above the
bare polling loop. The names never change, so everything but the stamp and the numbers is
encoded once.

The layout is plain CDR (XCDR1, little endian, the encapsulation every ROS 2 rmw uses for a
serialized message): header (stamp: int32 sec, uint32 nanosec; frame_id: uint32 length with
its NUL, the bytes, the NUL), then name (uint32 count; each string as frame_id, aligned to 4),
position, velocity, effort (uint32 count aligned to 4; the doubles aligned to 8). Alignment
counts from the end of the 4-byte encapsulation header. test_joint_state_cdr.py checks it
against rclpy's own deserializer.
"""

from __future__ import annotations

import struct
from typing import Sequence

ENCAPSULATION_CDR_LE = b'\x00\x01\x00\x00'


def _pad(offset: int, alignment: int) -> int:
    return (-offset) % alignment


def _string(text: str, offset: int) -> tuple[bytes, int]:
    raw = text.encode()
    pad = _pad(offset, 4)
    data = b'\0' * pad + struct.pack('<I', len(raw) + 1) + raw + b'\0'
    return data, offset + len(data)


class JointStateCdr:
    """encode(sec, nanosec, position, velocity, effort) -> the bytes of a JointState with these
    joint names and an empty frame_id. position and velocity have one value per joint; effort
    one per joint or none."""

    def __init__(self, names: Sequence[str], frame_id: str = ''):
        self.n = len(names)
        offset = 8                                      # after the stamp
        prefix, offset = _string(frame_id, offset)
        pad = _pad(offset, 4)
        prefix += b'\0' * pad + struct.pack('<I', self.n)
        offset += pad + 4
        for name in names:
            data, offset = _string(name, offset)
            prefix += data
        self._prefix = prefix
        # position and velocity: their count and padding depend on the offset only, which the
        # fixed names decide; so do effort's, with or without values
        self._position_head, offset = self._sequence_head(offset, self.n)
        offset += 8 * self.n
        self._velocity_head, offset = self._sequence_head(offset, self.n)
        offset += 8 * self.n
        self._effort_head, _ = self._sequence_head(offset, self.n)
        self._no_effort, _ = self._sequence_head(offset, 0)
        self._stamp = struct.Struct('<iI')
        self._doubles = struct.Struct(f'<{self.n}d')

    @staticmethod
    def _sequence_head(offset: int, count: int) -> tuple[bytes, int]:
        pad = _pad(offset, 4)
        head = b'\0' * pad + struct.pack('<I', count)
        offset += pad + 4
        if count:
            pad = _pad(offset, 8)
            head += b'\0' * pad
            offset += pad
        return head, offset

    def encode(self, sec: int, nanosec: int, position: Sequence[float],
               velocity: Sequence[float], effort: Sequence[float] | None = None) -> bytes:
        doubles = self._doubles.pack
        parts = [ENCAPSULATION_CDR_LE, self._stamp.pack(sec, nanosec), self._prefix,
                 self._position_head, doubles(*position), self._velocity_head,
                 doubles(*velocity)]
        if effort:
            parts += [self._effort_head, doubles(*effort)]
        else:
            parts.append(self._no_effort)
        return b''.join(parts)
