"""Conversions between our plain-numpy core and ROS messages (no logic beyond packing)."""

import math

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension


LEVEL = {
    'ok': DiagnosticStatus.OK,
    'warn': DiagnosticStatus.WARN,
    'error': DiagnosticStatus.ERROR,
    'stale': DiagnosticStatus.STALE,
}
LEVEL_NAMES = ('ok', 'warn', 'error', 'stale')  # by DiagnosticStatus level number
UNOBSERVED_VARIANCE = 1e6  # REP-145: a large variance for an orientation axis not measured


def joint_state(stamp, names, positions, velocities=None, out=None):
    """A JointState; `out`: one this built, filled again instead of building one (see
    wheel_effort); its effort is left to the caller."""
    msg = JointState() if out is None else out
    msg.header.stamp = stamp
    names = list(names)
    if out is None or msg.name != names:
        msg.name = names
    msg.position = [float(v) for v in positions]
    msg.velocity = [] if velocities is None else [float(v) for v in velocities]
    return msg


def stamp(t):
    """builtin_interfaces/Time of `t` seconds, rounded to the nanosecond."""
    sec, nanosec = divmod(int(round(t * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def stamp_seconds(stamp):
    return stamp.sec + stamp.nanosec * 1e-9


def wheel_effort(stamp, names, efforts, out=None):
    """The wheel command (/wheel_effort_cmd): efforts [N m] by joint name, stamped with the
    sample it answers (the convention of effort-commanded joints). `out`: a command this built
    for the same `names`, filled again instead of building one (a JointState costs about 30 us
    to build here; publishing copies the message, so a publisher may reuse it)."""
    msg = JointState() if out is None else out
    msg.header.stamp = stamp
    if out is None:
        msg.name = list(names)
    msg.effort = [float(v) for v in efforts]
    return msg


def wheel_efforts(msg, names):
    """The efforts of `names` (in that order) from a wheel command, or None unless each name
    appears once with an effort (the values are not checked: the bridge core judges them)."""
    if len(msg.effort) != len(msg.name) or len(set(msg.name)) != len(msg.name):
        return None
    index = {n: i for i, n in enumerate(msg.name)}
    if set(index) != set(names):
        return None
    return [msg.effort[index[n]] for n in names]


def name_index(msg):
    """Each name's position in a JointState (give it to the readers below to read one message
    several times without indexing it again)."""
    return {n: i for i, n in enumerate(msg.name)}


def joints_from_state(msg, names, index=None):
    """Positions of `names` (in that order) from a JointState; None if any is missing or not
    finite."""
    return _values(msg.position, names, name_index(msg) if index is None else index)


def velocities_from_state(msg, names, index=None):
    """Velocities of `names`, as joints_from_state; None also unless every joint has one."""
    if len(msg.velocity) != len(msg.name):
        return None
    return _values(msg.velocity, names, name_index(msg) if index is None else index)


def _values(column, names, index):
    """column[index[n]] for each of `names` as a float array; None if one is missing or not
    finite. `column` is read once (a message's field is a property)."""
    try:
        values = np.array([column[index[n]] for n in names], dtype=float)
    except (KeyError, IndexError):
        return None
    return values if np.all(np.isfinite(values)) else None


def labelled_array(values, labels, label='beta'):
    """Float64MultiArray whose layout names every entry ('Body.quantity'), so a bag is readable
    without this package."""
    msg = Float64MultiArray()
    msg.layout.dim = [
        MultiArrayDimension(
            label=label + ':' + ','.join(labels), size=len(values), stride=len(values)
        )
    ]
    msg.data = [float(v) for v in values]
    return msg


def array_values(msg, expected_size=None):
    values = np.array(msg.data, dtype=float)
    if expected_size is not None and values.size != expected_size:
        return None
    return values if np.all(np.isfinite(values)) else None


def pitch_quaternion(pitch):
    """Orientation (x, y, z, w) that /imu/data publishes for the authors' base pitch q_base: the
    rotation of imu_link (= base_link's axes, krang.urdf) in a gravity-aligned frame, REP-145, with
    yaw 0 (arbitrary: no magnetometer). About +y (left) by q_base, so REP-103's positive pitch,
    nose down, is q_base's positive, top tilting forward; upright (q_base = 0) is level, sitting
    on the caster (-1.76 rad) is tilted back past horizontal (krang_model/README.md,
    Conventions)."""
    return 0.0, math.sin(pitch / 2), 0.0, math.cos(pitch / 2)


def pitch_from_quaternion(x, y, z, w):
    """q_base from an /imu/data orientation: the inverse of pitch_quaternion, read off the
    direction of gravity in imu_link (R^T z), so any yaw the publisher chose drops out."""
    return math.atan2(2.0 * (w * y - x * z), 1.0 - 2.0 * (x * x + y * y))


def pitch_from_specific_force(x, y, z, gravity, tol=0.05):
    """q_base from an /imu/data linear_acceleration (x forward, z up at zero pitch, as can_bridge
    turns the DMU's specific force): at rest gravity's reaction reads (-g sin q, ., g cos q).
    Only the direction of gravity, so true only while the robot does not accelerate, but free of
    the gyro's drift. NaN (not measured) when the force is not gravity alone: its magnitude off
    `gravity` by more than `tol` of it, as for a driver that leaves the field zero."""
    if abs(math.sqrt(x * x + y * y + z * z) - gravity) > tol * gravity:
        return math.nan
    return math.atan2(-x, z)


def imu(stamp, frame_id, pitch, pitch_variance, angular_velocity, linear_acceleration, out=None):
    """sensor_msgs/Imu of a pitch-only orientation (pitch_quaternion); roll and yaw are not
    observed, so their variances are UNOBSERVED_VARIANCE. Vectors are (x, y, z). `out`: one this
    built for the same `frame_id`, filled again instead of building one (see wheel_effort)."""
    m = Imu() if out is None else out
    m.header.stamp = stamp
    m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w = pitch_quaternion(pitch)
    if out is None:
        m.header.frame_id = frame_id
        m.orientation_covariance = [
            UNOBSERVED_VARIANCE,
            0.0,
            0.0,
            0.0,
            float(pitch_variance),
            0.0,
            0.0,
            0.0,
            UNOBSERVED_VARIANCE,
        ]
    else:
        m.orientation_covariance[4] = float(pitch_variance)
    w, f = angular_velocity, linear_acceleration
    m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = (float(v) for v in w)
    m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = (
        float(v) for v in f
    )
    return m


def diagnostic_status(name, level, message, values=None, hardware_id=''):
    """One DiagnosticStatus; `level` is a name of LEVEL ('ok', 'warn', 'error', 'stale')."""
    status = DiagnosticStatus(
        level=LEVEL[level], name=name, message=message, hardware_id=hardware_id
    )
    status.values = [KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()]
    return status


def diagnostic_array(stamp, statuses):
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = list(statuses)
    return array


def diagnostics(stamp, name, level, message, values=None, hardware_id=''):
    """A DiagnosticArray of one status (diagnostic_status)."""
    return diagnostic_array(stamp, [diagnostic_status(name, level, message, values, hardware_id)])
