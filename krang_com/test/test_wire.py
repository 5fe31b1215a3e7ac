"""krang_ros.wire against rclpy's own serializer, the independent implementation: what wire
writes, rclpy reads back field for field, and what rclpy writes, wire reads; on random messages
(frame ids and joint names of every length modulo the alignment, non-ASCII names, empty and
unequal columns), a big-endian message (read through rclpy), and every truncation of a message
(WireError, never a value). Also the messages krang_ros.messages builds with it."""

import math
import random
import struct

import numpy as np
import pytest

pytest.importorskip('rclpy')

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402

from krang_core.pitch import pitch_from_quaternion  # noqa: E402
from krang_ros import messages, wire  # noqa: E402

NAMES = ['JLWheel', 'JRWheel', 'LJ1', 'torso', 'w', 'ü-joint', 'a' * 13, 'x']


def random_imu(rng):
    msg = Imu()
    msg.header.stamp.sec = rng.randrange(-(2**31), 2**31)
    msg.header.stamp.nanosec = rng.randrange(10**9)
    msg.header.frame_id = 'f' * rng.randrange(12)
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    o.x, o.y, o.z, o.w = (rng.uniform(-1, 1) for _ in range(4))
    w.x, w.y, w.z = (rng.uniform(-10, 10) for _ in range(3))
    a.x, a.y, a.z = (rng.uniform(-20, 20) for _ in range(3))
    for field in ('orientation', 'angular_velocity', 'linear_acceleration'):
        setattr(msg, field + '_covariance', [rng.uniform(0, 1) for _ in range(9)])
    return msg


def random_joint_state(rng):
    msg = JointState()
    msg.header.stamp.sec = rng.randrange(2**31)
    msg.header.stamp.nanosec = rng.randrange(10**9)
    msg.header.frame_id = 'b' * rng.randrange(6)
    msg.name = rng.sample(NAMES, rng.randrange(len(NAMES) + 1))
    n = len(msg.name)
    msg.position = [rng.uniform(-3, 3) for _ in range(rng.choice([0, n, n + 1]))]
    msg.velocity = [rng.uniform(-3, 3) for _ in range(rng.choice([0, n]))]
    msg.effort = [rng.uniform(-3, 3) for _ in range(rng.choice([0, n, max(0, n - 1)]))]
    return msg


def imu_fields(msg):
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    return (
        (msg.header.stamp.sec, msg.header.stamp.nanosec),
        (o.x, o.y, o.z, o.w),
        (w.x, w.y, w.z),
        (a.x, a.y, a.z),
    )


def joint_fields(msg):
    return (
        (msg.header.stamp.sec, msg.header.stamp.nanosec),
        tuple(msg.name),
        tuple(msg.position),
        tuple(msg.velocity),
        tuple(msg.effort),
    )


@pytest.mark.parametrize('seed', range(40))
def test_wire_reads_what_rclpy_writes_and_rclpy_reads_what_wire_writes(seed):
    rng = random.Random(seed)
    imu = random_imu(rng)
    assert tuple(wire.read_imu(serialize_message(imu))) == imu_fields(imu)
    raw = wire.imu_bytes(
        imu.header.stamp,
        imu.header.frame_id,
        imu_fields(imu)[1],
        imu.orientation_covariance,
        imu_fields(imu)[2],
        imu.angular_velocity_covariance,
        imu_fields(imu)[3],
        imu.linear_acceleration_covariance,
    )
    back = deserialize_message(raw, Imu)
    assert imu_fields(back) == imu_fields(imu) and back.header.frame_id == imu.header.frame_id
    for field in ('orientation', 'angular_velocity', 'linear_acceleration'):
        cov = field + '_covariance'
        assert getattr(back, cov).tolist() == getattr(imu, cov).tolist()

    joints = random_joint_state(rng)
    for _ in range(2):  # the second read finds the names in the cache
        assert tuple(wire.read_joint_state(serialize_message(joints))) == joint_fields(joints)
    raw = wire.joint_state_bytes(
        joints.header.stamp,
        joints.name,
        joints.position,
        joints.velocity,
        joints.effort,
        joints.header.frame_id,
    )
    back = deserialize_message(raw, JointState)
    assert joint_fields(back) == joint_fields(joints)
    assert back.header.frame_id == joints.header.frame_id


def test_name_lists_that_alternate_are_each_read_right():
    """The name cache: two senders' lists in turn, and more lists than it keeps."""
    msgs = [JointState(name=NAMES[k : k + 3], position=[float(k)] * 3) for k in range(6)]
    msgs += [JointState(name=[f'j{k}'], effort=[1.0]) for k in range(40)]
    for _ in range(2):
        for msg in msgs:
            assert tuple(wire.read_joint_state(serialize_message(msg))) == joint_fields(msg)


def test_a_big_endian_message_is_read_through_rclpy():
    """Built by hand here (CDR_BE encapsulation, struct's big-endian layout)."""
    raw = b'\x00\x00\x00\x00' + struct.pack('>iII', 7, 9, 2) + b'a\x00\x00\x00'
    raw += struct.pack('>4d9d3d9d3d9d', *range(37))
    sample = wire.read_imu(raw)
    assert sample.stamp == (7, 9) and sample.orientation == (0, 1, 2, 3)
    assert sample.angular_velocity == (13, 14, 15) and sample.linear_acceleration == (25, 26, 27)


@pytest.mark.parametrize(
    ('read', 'msg'),
    [
        (wire.read_imu, random_imu(random.Random(1))),
        (wire.read_joint_state, JointState(name=['a', 'bc'], position=[1.0, 2.0], effort=[3.0])),
    ],
)
def test_every_truncation_is_a_wire_error(read, msg):
    raw = serialize_message(msg)
    # rclpy's buffer may have slack after the message: its end is where rclpy reads it whole
    end = next(n for n in range(len(raw) + 1) if readable(raw[:n], type(msg)))
    read(raw[:end])
    for cut in range(end):
        with pytest.raises(wire.WireError):
            read(raw[:cut])


def readable(raw, kind):
    try:
        deserialize_message(raw, kind)
    except Exception:  # noqa: BLE001 - rclpy's own error types
        return False
    return True


def test_a_name_longer_than_the_message_is_a_wire_error():
    raw = bytearray(serialize_message(JointState(name=['abc'])))
    raw[24:28] = struct.pack('<I', 1000)  # the name's length
    with pytest.raises(wire.WireError):
        wire.read_joint_state(bytes(raw))


def test_the_imu_message_of_the_bridge():
    """messages.imu: pitch-only orientation, roll and yaw unobserved, frame and stamp kept."""
    raw = messages.imu(messages.stamp(2.5), 'imu_link', 0.3, 1e-4, (1, 2, 3), (4, 5, 6))
    msg = deserialize_message(raw, Imu)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (2, 500_000_000)
    assert msg.header.frame_id == 'imu_link'
    q = msg.orientation
    assert pitch_from_quaternion(q.x, q.y, q.z, q.w) == pytest.approx(0.3, abs=1e-15)
    big = messages.UNOBSERVED_VARIANCE
    assert msg.orientation_covariance.tolist() == [big, 0, 0, 0, 1e-4, 0, 0, 0, big]
    assert imu_fields(msg)[2:] == ((1, 2, 3), (4, 5, 6))
    assert not msg.angular_velocity_covariance.any()


def test_the_wheel_command_carries_its_stamp_and_efforts_by_name():
    raw = messages.wheel_effort(wire.Stamp(3, 4), ['JLWheel', 'JRWheel'], (1.5, -2.5))
    msg = deserialize_message(raw, JointState)
    assert joint_fields(msg) == ((3, 4), ('JLWheel', 'JRWheel'), (), (), (1.5, -2.5))
    sample = wire.read_joint_state(raw)
    assert messages.wheel_efforts(sample, ['JRWheel', 'JLWheel']) == [-2.5, 1.5]


def test_joint_readers_with_a_shared_index_agree_and_refuse_what_is_missing():
    msg = messages.joint_state(messages.stamp(0.0), ['a', 'b', 'c'], [1, 2, 3], [4, 5, 6])
    for read in (msg, wire.read_joint_state(serialize_message(msg))):
        index = messages.name_index(read)
        for shared in (None, index):
            assert messages.joints_from_state(read, ['c', 'a'], shared).tolist() == [3.0, 1.0]
            assert messages.velocities_from_state(read, ['b'], shared).tolist() == [5.0]
            assert messages.joints_from_state(read, ['a', 'x'], shared) is None  # one missing
    short = messages.joint_state(messages.stamp(0.0), ['a', 'b'], [1.0])  # b has no position
    assert messages.joints_from_state(short, ['b']) is None
    assert messages.velocities_from_state(short, ['a']) is None  # no velocities at all
    nan = messages.joint_state(messages.stamp(0.0), ['a'], [math.nan], [np.inf])
    assert messages.joints_from_state(nan, ['a']) is None
    assert messages.velocities_from_state(nan, ['a']) is None
