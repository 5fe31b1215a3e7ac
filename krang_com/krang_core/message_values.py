"""Values out of the robot's own messages, read by field name, so that nodes (rclpy messages) and
bag readers (decoded MCAP records) share one reading, of today's types and of older bags' alike.

Today's types are krang_com_interfaces' (docs/interfaces.md). Bags recorded before that package
carry the older forms, which are read here too and never written:
- /balanced_pose as sensor_msgs/JointState: the joints and `base_pitch` by name in `position`,
  each value's standard error in `effort`;
- /com_estimator/beta as std_msgs/Float64MultiArray (beta alone), and /com_estimator/posterior
  as one (row 0 beta, rows 1.. the covariance);
- /adrc_controller/mode and /can_bridge/drive_fault as std_msgs/String.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from krang_core.names import BASE_PITCH

#: ControllerMode's constants by mode name (krang_com_interfaces/msg/ControllerMode.msg); the
#: numbers are krang_adrc_controller.modes.MODE_CODES, which a test keeps equal
MODE_NAMES = ('safe_stop', 'sit', 'stand_up', 'balance', 'sit_down')


@dataclass(frozen=True)
class BalancedPoseValues:
    q_base: float  # [rad]
    joints: np.ndarray  # [rad], in the order asked for
    q_base_se: float | None  # standard error [rad]; None when not given or not positive
    joints_se: np.ndarray | None
    in_motion: bool = False  # read while the joints moved (BalancedPose.in_motion)


def _positive(value):
    value = float(value)
    return value if math.isfinite(value) and value > 0 else None


def balanced_pose_values(msg, joint_names):
    """The balanced pose in `msg` (a BalancedPose, or the JointState of older bags) with its
    joints in `joint_names` order; None unless every joint and the pitch are there and finite."""
    if hasattr(msg, 'joint_names'):
        index = {n: i for i, n in enumerate(msg.joint_names)}
        if len(index) != len(msg.joint_names) or any(j not in index for j in joint_names):
            return None
        joints = np.array([float(msg.positions[index[j]]) for j in joint_names])
        q_base = float(msg.base_pitch)
        q_se = _positive(msg.base_pitch_standard_error)
        se = msg.position_standard_errors
        joints_se = (
            np.array([float(se[index[j]]) for j in joint_names])
            if len(se) == len(msg.joint_names)
            else None
        )
        in_motion = bool(getattr(msg, 'in_motion', False))  # absent in older bags
    else:  # sensor_msgs/JointState: the pitch as one more joint, standard errors in effort
        index = {n: i for i, n in enumerate(msg.name)}
        names = list(joint_names) + [BASE_PITCH]
        if len(index) != len(msg.name) or any(n not in index for n in names):
            return None
        if len(msg.position) != len(msg.name):
            return None
        joints = np.array([float(msg.position[index[j]]) for j in joint_names])
        q_base = float(msg.position[index[BASE_PITCH]])
        has_se = len(msg.effort) == len(msg.name)
        q_se = _positive(msg.effort[index[BASE_PITCH]]) if has_se else None
        joints_se = (
            np.array([float(msg.effort[index[j]]) for j in joint_names]) if has_se else None
        )
        in_motion = False
    if not (math.isfinite(q_base) and np.all(np.isfinite(joints))):
        return None
    return BalancedPoseValues(q_base, joints, q_se, joints_se, in_motion)


def mass_model_values(msg, n_beta):
    """(beta, covariance or None) in `msg` (a MassModel, or an older bag's Float64MultiArray of
    beta alone or of beta and covariance); None unless beta has n_beta finite entries."""
    if hasattr(msg, 'beta'):
        beta = np.array(msg.beta, dtype=float)
        cov = np.array(msg.covariance, dtype=float)
        cov = cov.reshape(n_beta, n_beta) if cov.size == n_beta * n_beta else None
    else:
        data = np.array(msg.data, dtype=float)
        if data.size == n_beta:
            beta, cov = data, None
        elif data.size == (n_beta + 1) * n_beta:
            beta, cov = data[:n_beta], data[n_beta:].reshape(n_beta, n_beta)
        else:
            return None
    if beta.size != n_beta or not np.all(np.isfinite(beta)):
        return None
    if cov is not None and not np.all(np.isfinite(cov)):
        cov = None
    return beta, cov


def mode_name(msg):
    """The controller's mode name ('sit', 'balance', ...) in a ControllerMode or an older bag's
    String."""
    return str(msg.name) if hasattr(msg, 'mode') else str(msg.data)


def drive_fault_reason(msg):
    """The latched drive fault in a DriveFault or an older bag's String; '' when clear."""
    if hasattr(msg, 'active'):
        return str(msg.reason or 'drive fault') if msg.active else ''
    return str(msg.data)


def arm_fault_reason(msg):
    """The latched arm fault in an ArmFault; '' when clear."""
    return str(msg.reason or 'arm fault') if msg.active else ''
