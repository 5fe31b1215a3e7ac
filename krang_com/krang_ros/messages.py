"""Conversions between our plain-numpy core and ROS messages (no logic beyond packing)."""

import math

import numpy as np
from builtin_interfaces.msg import Time
from builtin_interfaces.msg import Duration
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from krang_com_interfaces.msg import (
    ArmFault,
    BalancedPose,
    ControllerMode,
    DriveFault,
    MassModel,
    StandEstimate,
)
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Header, MultiArrayDimension

from krang_core.pitch import pitch_quaternion

from . import wire


LEVEL = {
    'ok': DiagnosticStatus.OK,
    'warn': DiagnosticStatus.WARN,
    'error': DiagnosticStatus.ERROR,
    'stale': DiagnosticStatus.STALE,
}
LEVEL_NAMES = ('ok', 'warn', 'error', 'stale')  # by DiagnosticStatus level number
UNOBSERVED_VARIANCE = 1e6  # REP-145: a large variance for an orientation axis not measured


def joint_state(stamp, names, positions, velocities=None):
    """A JointState (its effort is left to the caller)."""
    msg = JointState()
    msg.header.stamp = stamp
    msg.name = list(names)
    msg.position = [float(v) for v in positions]
    if velocities is not None:
        msg.velocity = [float(v) for v in velocities]
    return msg


def stamp(t):
    """builtin_interfaces/Time of `t` seconds, rounded to the nanosecond."""
    sec, nanosec = divmod(int(round(t * 1e9)), 1_000_000_000)
    return Time(sec=sec, nanosec=nanosec)


def stamp_seconds(stamp):
    return stamp.sec + stamp.nanosec * 1e-9


def wheel_effort(stamp, names, efforts):
    """The wheel command (/wheel_effort_cmd) as CDR bytes (krang_ros.wire; publish them as they
    are): a JointState of efforts [N m] by joint name, stamped with the sample it answers (the
    convention of effort-commanded joints)."""
    return wire.joint_state_bytes(stamp, names, effort=[float(v) for v in efforts])


def wheel_efforts(msg, names):
    """The efforts of `names` (in that order) from a wheel command (a JointState or a
    wire.JointStateSample), or None unless each name appears once with an effort (the values are
    not checked: the bridge core judges them)."""
    if len(msg.effort) != len(msg.name) or len(set(msg.name)) != len(msg.name):
        return None
    index = {n: i for i, n in enumerate(msg.name)}
    if set(index) != set(names):
        return None
    return [msg.effort[index[n]] for n in names]


def name_index(msg):
    """Each name's position in a JointState or wire.JointStateSample (give it to the readers
    below to read one message several times without indexing it again)."""
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
    finite. `column` is read once (a message's field is a property); checked in Python, which
    costs less than numpy on a few values."""
    try:
        values = [float(column[index[n]]) for n in names]
    except (KeyError, IndexError):
        return None
    return np.array(values) if all(map(math.isfinite, values)) else None


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


def imu(stamp, frame_id, pitch, pitch_variance, angular_velocity, linear_acceleration):
    """sensor_msgs/Imu of a pitch-only orientation (pitch_quaternion) as CDR bytes
    (krang_ros.wire; publish them as they are); roll and yaw are not observed, so their variances
    are UNOBSERVED_VARIANCE; the rates' and accelerations' covariances are all zero ("unknown",
    as sensor_msgs/Imu defines). Vectors are (x, y, z)."""
    orientation_covariance = (UNOBSERVED_VARIANCE, 0.0, 0.0, 0.0, float(pitch_variance))
    orientation_covariance += (0.0, 0.0, 0.0, UNOBSERVED_VARIANCE)
    return wire.imu_bytes(
        stamp,
        frame_id,
        pitch_quaternion(pitch),
        orientation_covariance,
        [float(v) for v in angular_velocity],
        _ZERO_COVARIANCE,
        [float(v) for v in linear_acceleration],
        _ZERO_COVARIANCE,
    )


_ZERO_COVARIANCE = (0.0,) * 9


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


def balanced_pose(stamp, joint_names, point):
    """A BalancedPose from the detector's BalancedPoint (krang_adrc_controller.detector)."""
    joints_se = point.joints_se if point.joints_se is not None else []
    window = Duration(sec=int(point.window_s), nanosec=int(round((point.window_s % 1.0) * 1e9)))
    return BalancedPose(
        header=_header(stamp),
        joint_names=list(joint_names),
        positions=[float(v) for v in point.joints],
        position_standard_errors=[float(v) for v in joints_se],
        base_pitch=float(point.q_base),
        base_pitch_standard_error=float(point.q_base_se),
        base_pitch_std=float(point.q_base_std),
        base_pitch_imu_filter=float(point.q_base_filter),
        settle_window=window,
        samples=int(point.n_samples),
        in_motion=bool(point.in_motion),
    )


def mass_model(stamp, body_names, beta, covariance=None, source='', poses=0):
    """A MassModel: beta by body (m, mx, my, mz each), its covariance row-major if known."""
    cov = [] if covariance is None else np.asarray(covariance, dtype=float).ravel().tolist()
    return MassModel(
        header=_header(stamp),
        body_names=list(body_names),
        beta=[float(v) for v in beta],
        covariance=cov,
        source=source,
        poses=int(poses),
    )


def controller_mode(stamp, name):
    """A ControllerMode for a mode name ('sit', 'balance', ...: krang_adrc_controller.modes)."""
    return ControllerMode(
        header=_header(stamp), mode=getattr(ControllerMode, name.upper()), name=name
    )


def stand_estimate(stamp, tries, tries_max, com_angle_error, window):
    """A StandEstimate: a caught stand-up's try count and CoM-angle error estimate (rad), and the
    stand `window` (min, max) it refers to (rad)."""
    return StandEstimate(
        header=_header(stamp),
        tries=int(tries),
        tries_max=int(tries_max),
        com_angle_error=float(com_angle_error),
        stand_window_min=float(window[0]),
        stand_window_max=float(window[1]),
    )


def drive_fault(stamp, reason):
    """A DriveFault: active with its reason, or clear when reason is ''."""
    return DriveFault(header=_header(stamp), active=bool(reason), reason=reason)


def arm_fault(stamp, reason, joints):
    """An ArmFault: active with its reason and joints, or clear when reason is ''."""
    return ArmFault(header=_header(stamp), active=bool(reason), joints=list(joints), reason=reason)


def _header(stamp):
    return Header(stamp=stamp)
