"""Base pitch q_base and the orientation and specific force /imu/data carries: the conversions
every node, offline loader and test shares (plain math, no ROS types)."""

import math


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
