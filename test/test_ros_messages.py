"""krang_ros.messages: a message filled again (`out`, the nodes' hot path) equals one built new,
whatever the message it reuses held before; the joint readers with and without a shared index."""

import math

import numpy as np
import pytest

pytest.importorskip('rclpy')

from krang_ros import messages  # noqa: E402


def fields(msg):
    """Every field of a message as plain Python values (arrays to lists), recursively."""
    if hasattr(msg, 'get_fields_and_field_types'):
        return {k: fields(getattr(msg, k)) for k in msg.get_fields_and_field_types()}
    if isinstance(msg, (list, tuple)) or hasattr(msg, 'tolist'):
        return [fields(v) for v in (msg.tolist() if hasattr(msg, 'tolist') else msg)]
    return msg


def test_a_refilled_imu_equals_a_new_one():
    first = messages.imu(messages.stamp(1.0), 'imu_link', 0.3, 1e-4, (1, 2, 3), (4, 5, 6))
    args = (messages.stamp(2.5), 'imu_link', -0.2, 2e-5, (0.1, -0.2, 0.3), (0.4, 9.8, -0.6))
    again = messages.imu(*args, out=first)
    assert again is first
    assert fields(again) == fields(messages.imu(*args))


def test_a_refilled_joint_state_equals_a_new_one():
    old = messages.joint_state(messages.stamp(1.0), ['a', 'b', 'c'], [1, 2, 3], [4, 5, 6])
    old.effort = [7.0, 8.0, 9.0]
    # other names, no velocities: nothing of the old message may remain but what the caller sets
    args = (messages.stamp(3.0), ['b', 'd'], [0.5, 0.25])
    again = messages.joint_state(*args, out=old)
    again.effort = [1.0, 2.0]
    new = messages.joint_state(*args)
    new.effort = [1.0, 2.0]
    assert again is old and fields(again) == fields(new)
    assert list(again.velocity) == []


def test_a_refilled_wheel_command_equals_a_new_one():
    wheels = ['JLWheel', 'JRWheel']
    first = messages.wheel_effort(messages.stamp(1.0), wheels, (1.5, -2.5))
    again = messages.wheel_effort(messages.stamp(2.0), wheels, (0.25, 0.5), out=first)
    assert again is first
    assert fields(again) == fields(messages.wheel_effort(messages.stamp(2.0), wheels, (0.25, 0.5)))


def test_joint_readers_with_a_shared_index_agree_and_refuse_what_is_missing():
    msg = messages.joint_state(messages.stamp(0.0), ['a', 'b', 'c'], [1, 2, 3], [4, 5, 6])
    index = messages.name_index(msg)
    for shared in (None, index):
        assert messages.joints_from_state(msg, ['c', 'a'], shared).tolist() == [3.0, 1.0]
        assert messages.velocities_from_state(msg, ['b'], shared).tolist() == [5.0]
        assert messages.joints_from_state(msg, ['a', 'x'], shared) is None  # a name missing
    short = messages.joint_state(messages.stamp(0.0), ['a', 'b'], [1.0])  # b has no position
    assert messages.joints_from_state(short, ['b']) is None
    assert messages.velocities_from_state(short, ['a']) is None  # no velocities at all
    nan = messages.joint_state(messages.stamp(0.0), ['a'], [math.nan], [np.inf])
    assert messages.joints_from_state(nan, ['a']) is None
    assert messages.velocities_from_state(nan, ['a']) is None
