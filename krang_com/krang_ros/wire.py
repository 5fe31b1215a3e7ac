"""The control path's messages as the bytes DDS carries (CDR), read and written without building
rclpy message objects.

rclpy turns every message it takes into a Python message object and every message it publishes
back into C, field by field, through the generated classes' checking setters. On this machine a
sensor_msgs/Imu costs 70 us to take and 20 us to publish, a 19-joint JointState 46 and 17, and
a node on the control path takes or publishes two to three of them per sample. As bytes (rclpy's
`raw=True` subscriptions, `publish(bytes)`) each costs a few us, and reading the few fields a node
needs from them, or writing them, a few more (bench/bench_wire.py).

The layout is the one ROS 2's middlewares use for these types: XCDR1 ("plain CDR"), a 4-byte
encapsulation header, then the fields in order, each primitive aligned to its size counted from
the end of the header; a string is a uint32 length (with its NUL) and its bytes, a sequence a
uint32 count and its elements (a double sequence is aligned to 8 only when it has elements).
We write little-endian, which every reader accepts (the header says so). A message in any other
encapsulation (a big-endian host, XCDR2) is read through rclpy's own deserializer, and one that
does not parse raises WireError: the caller treats it as the malformed message it is.
test/test_wire.py checks both directions against rclpy's serializer.
"""

from __future__ import annotations

import functools
import struct
from typing import NamedTuple, Sequence

from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState

CDR_LE = b'\x00\x01\x00\x00'  # PLAIN_CDR, little endian, no options
_ORIGIN = len(CDR_LE)  # alignment counts from here
_HEADER = struct.Struct('<iII')  # stamp.sec, stamp.nanosec, frame_id's length
_STAMP = struct.Struct('<iI')
_UINT32 = struct.Struct('<I')
# Imu after its header: orientation (x y z w) and its covariance, angular velocity and its
# covariance, linear acceleration and its covariance
_IMU_BODY = struct.Struct('<4d9d3d9d3d9d')
_NAME_CACHE_SIZE = 16  # distinct joint name lists read_joint_state remembers


class WireError(ValueError):
    """The bytes are not a message of the expected type."""


class Stamp(NamedTuple):
    """A header stamp (builtin_interfaces/Time's fields)."""

    sec: int
    nanosec: int


class ImuSample(NamedTuple):
    """The fields of a sensor_msgs/Imu the control path reads; vectors as tuples."""

    stamp: Stamp
    orientation: tuple  # (x, y, z, w)
    angular_velocity: tuple  # (x, y, z)
    linear_acceleration: tuple  # (x, y, z)


class JointStateSample(NamedTuple):
    """A sensor_msgs/JointState, its columns as tuples (the field names of the message, so
    krang_ros.messages reads either)."""

    stamp: Stamp
    name: tuple
    position: tuple
    velocity: tuple
    effort: tuple


def _pad(offset: int, size: int) -> int:
    """Bytes of padding before a primitive of `size` at `offset` (from the buffer's start)."""
    return -(offset - _ORIGIN) % size


def _string(text: str) -> bytes:
    """A CDR string without its alignment: length with the NUL, the bytes, the NUL."""
    data = text.encode() + b'\x00'
    return _UINT32.pack(len(data)) + data


# ---- sensor_msgs/Imu --------------------------------------------------------------------------
def imu_bytes(
    stamp,
    frame_id: str,
    orientation: Sequence[float],
    orientation_covariance: Sequence[float],
    angular_velocity: Sequence[float],
    angular_velocity_covariance: Sequence[float],
    linear_acceleration: Sequence[float],
    linear_acceleration_covariance: Sequence[float],
) -> bytes:
    """A sensor_msgs/Imu as CDR; `stamp` has .sec and .nanosec (Stamp or a Time)."""
    return (
        CDR_LE
        + _STAMP.pack(stamp.sec, stamp.nanosec)
        + _imu_head(frame_id)
        + _IMU_BODY.pack(
            *orientation,
            *orientation_covariance,
            *angular_velocity,
            *angular_velocity_covariance,
            *linear_acceleration,
            *linear_acceleration_covariance,
        )
    )


@functools.lru_cache(maxsize=64)
def _imu_head(frame_id: str) -> bytes:
    """An Imu's bytes between its stamp and its body: the frame id, and the padding to 8."""
    head = _string(frame_id)
    return head + bytes(_pad(_ORIGIN + _STAMP.size + len(head), 8))


def read_imu(raw: bytes) -> ImuSample:
    """The ImuSample of a serialized sensor_msgs/Imu; WireError if it is not one."""
    if raw[:2] != CDR_LE[:2]:
        return _imu_sample(_deserialize(raw, Imu, 'sensor_msgs/Imu'))
    try:
        sec, nanosec, length = _HEADER.unpack_from(raw, _ORIGIN)
        offset = _ORIGIN + _HEADER.size + length
        v = _IMU_BODY.unpack_from(raw, offset + _pad(offset, 8))
    except struct.error as err:
        raise WireError(f'not a sensor_msgs/Imu: {err}') from None
    return ImuSample(Stamp(sec, nanosec), v[0:4], v[13:16], v[25:28])


def _imu_sample(msg) -> ImuSample:
    o, w, a = msg.orientation, msg.angular_velocity, msg.linear_acceleration
    return ImuSample(
        Stamp(msg.header.stamp.sec, msg.header.stamp.nanosec),
        (o.x, o.y, o.z, o.w),
        (w.x, w.y, w.z),
        (a.x, a.y, a.z),
    )


# ---- sensor_msgs/JointState -------------------------------------------------------------------
def joint_state_bytes(
    stamp,
    names: Sequence[str],
    position: Sequence[float] = (),
    velocity: Sequence[float] = (),
    effort: Sequence[float] = (),
    frame_id: str = '',
) -> bytes:
    """A sensor_msgs/JointState as CDR; `stamp` has .sec and .nanosec (Stamp or a Time)."""
    counts = (len(position), len(velocity), len(effort))
    head, columns = _joint_state_layout(frame_id, tuple(names), counts)
    return (
        CDR_LE
        + _STAMP.pack(stamp.sec, stamp.nanosec)
        + head
        + columns.pack(counts[0], *position, counts[1], *velocity, counts[2], *effort)
    )


@functools.lru_cache(maxsize=64)
def _joint_state_layout(frame_id: str, names: tuple, counts: tuple) -> tuple[bytes, struct.Struct]:
    """A JointState's bytes between its stamp and its columns (the frame id and the names, the
    same in every message of a sender), and the struct of the columns with their counts and
    padding."""
    head = bytearray(_string(frame_id))
    head += bytes(_pad(_ORIGIN + _STAMP.size + len(head), 4)) + _UINT32.pack(len(names))
    for name in names:
        head += bytes(_pad(_ORIGIN + _STAMP.size + len(head), 4)) + _string(name)
    offset, fmt = _ORIGIN + _STAMP.size + len(head), '<'
    for count in counts:
        pad = _pad(offset, 4)
        fmt, offset = fmt + f'{pad}xI', offset + pad + 4
        if count:
            pad = _pad(offset, 8)
            fmt, offset = fmt + f'{pad}x{count}d', offset + pad + 8 * count
    return bytes(head), struct.Struct(fmt)


@functools.lru_cache(maxsize=64)
def _doubles(count: int) -> struct.Struct:
    return struct.Struct(f'<{count}d')


_decoded_names: dict = {}  # the name sequence's bytes -> (names, the offset after them - start)


def read_joint_state(raw: bytes) -> JointStateSample:
    """The JointStateSample of a serialized sensor_msgs/JointState; WireError if it is not
    one."""
    if raw[:2] != CDR_LE[:2]:
        return _joint_state_sample(_deserialize(raw, JointState, 'sensor_msgs/JointState'))
    try:
        sec, nanosec, length = _HEADER.unpack_from(raw, _ORIGIN)
        offset = _ORIGIN + _HEADER.size + length
        names, offset = _read_names(raw, offset)
        columns = []
        for _ in range(3):  # position, velocity, effort
            offset += -(offset - _ORIGIN) % 4
            (count,) = _UINT32.unpack_from(raw, offset)
            offset += 4
            if count:
                offset += -(offset - _ORIGIN) % 8
                doubles = _doubles(count)
                columns.append(doubles.unpack_from(raw, offset))
                offset += doubles.size
            else:
                columns.append(())
    except (struct.error, UnicodeDecodeError) as err:
        raise WireError(f'not a sensor_msgs/JointState: {err}') from None
    return JointStateSample(Stamp(sec, nanosec), names, *columns)


def _read_names(raw: bytes, offset: int) -> tuple[tuple, int]:
    """The name sequence at `offset` and the offset after it. The names of one sender repeat in
    every message: the first message parses them, the next ones look their bytes up."""
    start = offset + _pad(offset, 4)
    (count,) = _UINT32.unpack_from(raw, start)
    for names_bytes, (names, size) in list(_decoded_names.items()):  # another thread may clear it
        if raw.startswith(names_bytes, start):
            return names, start + size
    names, offset = [], start + 4
    for _ in range(count):
        offset += _pad(offset, 4)
        (length,) = _UINT32.unpack_from(raw, offset)
        end = offset + 4 + length
        if length == 0 or end > len(raw) or raw[end - 1] != 0:
            raise struct.error(f'a name of {length} bytes at offset {offset} does not fit')
        names.append(raw[offset + 4 : end - 1].decode())
        offset = end
    names = tuple(names)
    if len(_decoded_names) >= _NAME_CACHE_SIZE:
        _decoded_names.clear()
    _decoded_names[raw[start:offset]] = (names, offset - start)
    return names, offset


def _joint_state_sample(msg) -> JointStateSample:
    return JointStateSample(
        Stamp(msg.header.stamp.sec, msg.header.stamp.nanosec),
        tuple(msg.name),
        tuple(msg.position),
        tuple(msg.velocity),
        tuple(msg.effort),
    )


def _deserialize(raw: bytes, kind, name: str):
    """rclpy's deserializer, for an encapsulation this module does not read."""
    try:
        return deserialize_message(raw, kind)
    except Exception as err:  # noqa: BLE001 - rclpy raises its own error types
        raise WireError(f'not a {name}: {err}') from None
