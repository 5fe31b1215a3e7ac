"""The list of excitatory poses the online session walks through, one `next_pose` at a time."""

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


@dataclass(frozen=True)
class StraightLineMove:
    """A coordinated move in joint space: every joint arrives at the same time, so the path is the
    straight line between the poses (whose balance stays away from the caster when both ends do),
    not the per-joint dash the modules would make at their own top speeds."""

    start: np.ndarray
    goal: np.ndarray
    duration: float

    @classmethod
    def plan(cls, start, goal, velocity_limit, speed_fraction=0.8):
        start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
        return cls(start, goal, float(move_times(start, goal, velocity_limit, speed_fraction)))

    def at(self, t):
        s = 1.0 if self.duration <= 0 else min(max(t / self.duration, 0.0), 1.0)
        return self.start + s * (self.goal - self.start)


def move_times(start, goals, velocity_limit, speed_fraction=0.8):
    """Duration (s) of the straight-line move from `start` to each goal (rows, or one pose): the
    slowest joint at `speed_fraction` of its limit sets the time."""
    d = np.abs(np.asarray(goals, dtype=float) - np.asarray(start, dtype=float))
    speed = speed_fraction * np.asarray(velocity_limit, dtype=float)
    return (d / speed).max(axis=-1, initial=0.0)
