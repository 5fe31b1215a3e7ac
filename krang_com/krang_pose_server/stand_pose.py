"""The pose the robot stands up in, and the re-pose after a stand-up that fell back on its caster.

The controller stands up only when the CoM angle its beta predicts on the caster lies in its stand
window (``modes.stand_error_min_rad`` .. ``stand_error_max_rad``, -12 .. 0 deg). An operator sets
the waist so that the angle is the window's middle (``stand_pose``). With a wrong beta the true
angle can lie anywhere: the prior's standard deviation of it is 76 mrad at the Table II pose, and
a truth 1.3 sigma off (7500) sits with its CoM only 6 mrad behind the axle. Such a robot cannot
balance clear of its caster and, once fallen back on it, cannot brake (its deceleration is g
times that angle), so it rolls on until a safety stop.

A caught stand-up measured the CoM-angle error within 0.2 s of lift-off (the controller's
``stand_estimate``). ``restand_pose`` moves the waist so that the CoM angle corrected by that
estimate is the window's middle again, or as close as the window allows: the CoM moves back, the
rolling robot can brake, and the retry stands up with the CoM where an operator would have put it
had they known. The CoM only ever moves back: a re-pose never brings a sitting robot's CoM nearer
its axle.
"""

from __future__ import annotations

import numpy as np

from krang_model.com import balance_pitch
from krang_model.drivetrain import drivetrain

#: the waist angles a stand pose or a re-pose may use, rad (the URDF's upper limit; the waist
#: reaches down to 0, far beyond any stand pose)
WAIST_RANGE = (1.5, 2.88)
#: a re-pose keeps the predicted CoM angle this fraction of the stand window above its lower edge
WINDOW_EDGE = 0.1
#: ... and moves the CoM back by at least this angle, rad (less is within the estimate's scatter)
MIN_CHANGE_RAD = 0.005


def caster_com_angle(robot, joints, beta, caster_pitch=None) -> np.ndarray:
    """The CoM angle (rad, negative behind the axle) `beta` predicts for each pose (rows of
    `joints`) sitting on the caster."""
    caster = drivetrain(robot).caster_pitch if caster_pitch is None else caster_pitch
    return caster - balance_pitch(robot, np.atleast_2d(joints), beta)


def stand_pose(robot, beta, base, target_theta_rad, caster_pitch=None, waist_range=WAIST_RANGE):
    """`base` with the waist set so that the CoM angle `beta` predicts on the caster is
    `target_theta_rad`; `base` itself if no waist in `waist_range` gives it. Bisection (the angle
    rises with the waist angle over the range)."""
    base = np.array(base, dtype=float)

    def theta_sit(w):
        p = base.copy()
        p[0] = w
        return caster_com_angle(robot, p, beta, caster_pitch)[0]

    lo, hi = waist_range
    if not theta_sit(lo) <= target_theta_rad <= theta_sit(hi):
        return base
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if theta_sit(mid) < target_theta_rad:
            lo = mid
        else:
            hi = mid
    out = base.copy()
    out[0] = 0.5 * (lo + hi)
    return out


def restand_pose(
    robot, beta, joints, com_angle_error, window, caster_pitch=None, waist_range=WAIST_RANGE
):
    """The pose to retry a stand-up in after a caught one: `joints` with the waist moved so that
    the CoM angle on the caster by `beta`, less the controller's `com_angle_error` estimate, is
    the middle of the stand `window` (min, max), kept WINDOW_EDGE of the window above its lower
    edge. None when the CoM needs no moving back by MIN_CHANGE_RAD or more (it already lies about
    that far behind the axle) or no waist in `waist_range` moves it back."""
    lo, hi = window
    target = max(0.5 * (lo + hi) + com_angle_error, lo + WINDOW_EDGE * (hi - lo))
    joints = np.asarray(joints, float)
    if caster_com_angle(robot, joints, beta, caster_pitch)[0] <= target + MIN_CHANGE_RAD:
        return None
    theta_lo = caster_com_angle(robot, np.r_[waist_range[0], joints[1:]], beta, caster_pitch)[0]
    pose = stand_pose(robot, beta, joints, max(target, theta_lo), caster_pitch, waist_range)
    return None if pose[0] == joints[0] else pose
