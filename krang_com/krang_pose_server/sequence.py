"""The list of excitatory poses the online session walks through, one `next_pose` at a time, and
the pace of a move between two poses."""

from dataclasses import dataclass

import numpy as np

from krang_model.poses import load_poses


@dataclass(frozen=True)
class PoseTarget:
    index: int  # 0-based position in the list
    total: int
    joints: np.ndarray  # pose order, rad

    @property
    def remaining(self):
        return self.total - self.index - 1

    def describe(self):
        return f'pose {self.index + 1}/{self.total}; {self.remaining} left'


class PoseSequence:
    """Poses in order, validated against the robot's joint limits when loaded."""

    def __init__(self, joints, robot):
        joints = np.atleast_2d(np.asarray(joints, dtype=float))
        if joints.shape[1] != len(robot.pose_joints):
            raise ValueError(
                f'poses have {joints.shape[1]} joints, {robot.name} has {len(robot.pose_joints)}'
            )
        if not np.all(np.isfinite(joints)):
            raise ValueError('poses contain NaN or inf')
        outside = np.flatnonzero(np.any((joints < robot.lower) | (joints > robot.upper), axis=1))
        if outside.size:
            raise ValueError(f'poses {outside[:10].tolist()} are outside the joint limits')
        self.joints = joints
        self.cursor = -1

    @classmethod
    def from_csv(cls, path, robot, columns):
        _, joints, _ = load_poses(path, columns)
        return cls(joints, robot)

    def __len__(self):
        return len(self.joints)

    def advance(self):
        """The next pose, or None when the list is exhausted."""
        if self.cursor + 1 >= len(self.joints):
            return None
        self.cursor += 1
        return self.current()

    def current(self):
        if self.cursor < 0:
            return None
        return PoseTarget(self.cursor, len(self.joints), self.joints[self.cursor])

    def reset(self):
        self.cursor = -1


#: The fastest a move may carry the balance pitch its path predicts, rad/s. The body follows its
#: balance pitch with a lag of about the balance loop's time constant (0.4-0.5 s), and the wheels
#: hold that lag against gravity. On the full-body plant with a gear-hard chain (torque 0.6 of the
#: commanded, 8 N m of dry friction per wheel) moves that swept the balance pitch at 0.2-0.3 rad/s
#: lagged 0.10-0.19 rad behind it with both wheels at the drive's current limit, and one fell;
#: at up to 0.13 rad/s the lag stayed under 0.08 rad and the current at 25-43 A (docs/mujoco.md).
MAX_BALANCE_RATE_RAD_S = 0.1

#: segments of a candidate move's path at which the adaptive choice predicts its balance pitch
#: (its caster margin, for 1000 candidates at once)
PATH_SEGMENTS = 8

#: ... and of the move the pose server plans: the steepest of 8 segments understated the steepest
#: point of the path by up to 30 % over pool moves, of 64 by up to 4 %
PACE_SEGMENTS = 64


def path_points(start, goals, segments=PATH_SEGMENTS):
    """The poses along the straight-line moves from `start` to each goal: (segments + 1, N, n)
    for goals (N, n), or (segments + 1, n) for one goal."""
    start, goals = np.asarray(start, dtype=float), np.asarray(goals, dtype=float)
    u = np.linspace(0.0, 1.0, segments + 1).reshape(-1, *(1,) * goals.ndim)
    return start + u * (goals - start)


def move_times(
    start, goals, velocity_limit, speed_fraction=0.8, path_pitch=None, max_balance_rate=0.0
):
    """Duration (s) of the straight-line move from `start` to each goal (rows, or one pose): the
    slowest joint at `speed_fraction` of its limit sets the time, unless the balance pitch
    predicted along the path (`path_pitch`, (segments + 1, ...) at ``path_points``) would then
    move faster than `max_balance_rate` (rad/s, 0 = no limit) on some segment."""
    d = np.abs(np.asarray(goals, dtype=float) - np.asarray(start, dtype=float))
    speed = speed_fraction * np.asarray(velocity_limit, dtype=float)
    joint_time = (d / speed).max(axis=-1, initial=0.0)
    if path_pitch is None or not max_balance_rate:
        return joint_time
    pitch = np.asarray(path_pitch, dtype=float)
    steepest = np.abs(np.diff(pitch, axis=0)).max(axis=0)  # rad per segment
    return np.maximum(joint_time, steepest * (len(pitch) - 1) / max_balance_rate)


@dataclass(frozen=True)
class StraightLineMove:
    """A coordinated move in joint space: every joint arrives at the same time, so the path is the
    straight line between the poses (whose balance stays away from the caster when both ends do),
    not the per-joint dash the modules would make at their own top speeds. Its pace: the joints'
    speed limits, and the balance pitch's (``MAX_BALANCE_RATE_RAD_S``)."""

    start: np.ndarray
    goal: np.ndarray
    duration: float

    @classmethod
    def plan(
        cls,
        start,
        goal,
        velocity_limit,
        speed_fraction=0.8,
        balance=None,
        max_balance_rate=MAX_BALANCE_RATE_RAD_S,
    ):
        """`balance`: joints (N, n) -> the balance pitch the current mass model predicts (N,)
        (``krang_model.com.balance_pitch``); None: the joints' limits alone."""
        start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
        pitch = None if balance is None else balance(path_points(start, goal, PACE_SEGMENTS))
        duration = move_times(start, goal, velocity_limit, speed_fraction, pitch, max_balance_rate)
        return cls(start, goal, float(duration))

    def at(self, t):
        s = 1.0 if self.duration <= 0 else min(max(t / self.duration, 0.0), 1.0)
        return self.start + s * (self.goal - self.start)
