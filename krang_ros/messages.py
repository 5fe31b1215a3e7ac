"""Conversions between our plain-numpy core and ROS messages (no logic beyond packing)."""
import math

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from .names import BASE_PITCH  # noqa: F401

LEVEL = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN, 'error': DiagnosticStatus.ERROR,
         'stale': DiagnosticStatus.STALE}


def joint_state(stamp, names, positions, velocities=None):
    msg = JointState()
    msg.header.stamp = stamp
    msg.name = list(names)
    msg.position = [float(v) for v in positions]
    if velocities is not None:
        msg.velocity = [float(v) for v in velocities]
    return msg


def joints_from_state(msg, names):
    """Positions of `names` (in that order) from a JointState; None if any is missing or not finite."""
    index = {n: i for i, n in enumerate(msg.name)}
    if any(n not in index or index[n] >= len(msg.position) for n in names):
        return None
    values = np.array([msg.position[index[n]] for n in names], dtype=float)
    return values if np.all(np.isfinite(values)) else None


def velocities_from_state(msg, names):
    index = {n: i for i, n in enumerate(msg.name)}
    if len(msg.velocity) != len(msg.name):
        return None
    values = np.array([msg.velocity[index[n]] for n in names if n in index], dtype=float)
    return values if values.size == len(names) and np.all(np.isfinite(values)) else None


def labelled_array(values, labels, label='beta'):
    """Float64MultiArray whose layout names every entry ('Body.quantity'), as DESIGN §5 asks."""
    msg = Float64MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label + ':' + ','.join(labels), size=len(values), stride=len(values))]
    msg.data = [float(v) for v in values]
    return msg


def array_values(msg, expected_size=None):
    values = np.array(msg.data, dtype=float)
    if expected_size is not None and values.size != expected_size:
        return None
    return values if np.all(np.isfinite(values)) else None


def pitch_quaternion(pitch):
    """(x, y, z, w) of the base pitch as a rotation about frame 0's y axis (nose down is +pitch:
    q_base grows as the robot tips forward, a right-handed rotation about +y of frame 0)."""
    return 0.0, math.sin(pitch / 2), 0.0, math.cos(pitch / 2)


def pitch_from_quaternion(x, y, z, w):
    return 2.0 * math.atan2(y, w)


def diagnostics(stamp, name, level, message, values=None, hardware_id=''):
    array = DiagnosticArray()
    array.header.stamp = stamp
    status = DiagnosticStatus(level=LEVEL[level], name=name, message=message, hardware_id=hardware_id)
    status.values = [KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()]
    array.status = [status]
    return array
