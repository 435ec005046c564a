"""JointStateCdr against rclpy's own (de)serializer: the bytes a node publishes raw must be the
JointState a subscriber reads, for any number of joints, names of any length, NaN velocities,
with and without efforts."""

from __future__ import annotations

import math
import struct

import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import JointState
from stepper_drivers.ros.joint_state_cdr import JointStateCdr


def same(a: float, b: float) -> bool:
    return struct.pack('<d', a) == struct.pack('<d', b)       # NaN and -0.0 included


@pytest.mark.parametrize('n', range(1, 10))
@pytest.mark.parametrize('with_effort', [False, True])
def test_a_subscriber_reads_what_was_encoded(n, with_effort):
    # names of every length modulo 4 and 8, so every padding case occurs
    names = [f'j{"x" * ((i * 3 + n) % 9)}_{i}' for i in range(n)]
    position = [(-1) ** i * (i + 0.125) * 1e3 for i in range(n)]
    velocity = [math.nan if i % 3 == 1 else -0.0 if i % 3 == 2 else 1.5 * i for i in range(n)]
    effort = [0.25 * i for i in range(n)] if with_effort else None
    raw = JointStateCdr(names).encode(1_795_500_000, 999_999_999, position, velocity, effort)
    msg = deserialize_message(raw, JointState)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_795_500_000, 999_999_999)
    assert msg.header.frame_id == '' and list(msg.name) == names
    assert all(map(same, msg.position, position)) and len(msg.position) == n
    assert all(map(same, msg.velocity, velocity)) and len(msg.velocity) == n
    assert list(msg.effort) == (effort or [])


def test_the_bytes_are_rclpys_but_for_padding_and_slack():
    """rclpy's buffer leaves padding bytes unset and ends with slack (an estimated size):
    compare the bytes that carry data."""
    names = ['rd4_joint1', 'rd4_joint22', 'x']
    position, velocity = [1.0, -2.5, 3.25], [0.5, math.nan, 0.0]
    ours = JointStateCdr(names).encode(7, 8, position, velocity)
    theirs = serialize_message(deserialize_message(ours, JointState))
    assert len(theirs) >= len(ours)
    padding = {i for i in range(len(ours)) if ours[i] == 0}     # where a difference may be
    assert all(ours[i] == theirs[i] for i in range(len(ours)) if i not in padding)


def test_a_negative_stamp_and_non_ascii_names():
    raw = JointStateCdr(['Gelenk_ä', 'ß']).encode(-3, 5, [0.0, 1.0], [2.0, 3.0])
    msg = deserialize_message(raw, JointState)
    assert msg.header.stamp.sec == -3 and list(msg.name) == ['Gelenk_ä', 'ß']


def test_a_wrong_number_of_values_is_an_error():
    with pytest.raises(struct.error):
        JointStateCdr(['a', 'b']).encode(0, 0, [1.0], [1.0, 2.0])
