"""One balanced pose in, one beta out: the glue shared by the com_estimator node and `krang
relearn`, so that replaying a bag runs exactly the computation the robot ran. `method` is any name
of the estimator registry (krang_com_estimator.make_estimator)."""

from dataclasses import dataclass, field

import numpy as np

from krang_model.com import com_frame0

from .registry import make_estimator
from .rows import NoiseModel


@dataclass
class OnlineLearner:
    robot: object
    beta0: np.ndarray
    method: str = 'map-online'
    noise: NoiseModel = field(default_factory=NoiseModel)

    def __post_init__(self):
        self.beta0 = np.asarray(self.beta0, dtype=float)
        self.estimator = make_estimator(self.method, self.robot, self.beta0, noise=self.noise)
        self.history = [self.beta0.copy()]
        self.poses = []
        self.moving_points = 0  # points read while moving, learned between the poses

    @property
    def beta(self):
        return self.estimator.beta

    def add_balanced_pose(self, q_base, joints, sigma=None, in_motion=False):
        """Learn from one balanced pose (q_base in rad, joints in pose order; sigma: its pitch
        standard error in rad, if known); returns the new beta. A point read while moving
        (`in_motion`) is learned alike but is no pose: ``poses`` and ``history`` (a beta per
        pose, as the node publishes them) hold the points at rest."""
        joints = np.asarray(joints, dtype=float)
        if (
            joints.shape != (len(self.robot.pose_joints),)
            or not np.all(np.isfinite(joints))
            or not np.isfinite(q_base)
        ):
            raise ValueError(
                f'balanced pose needs {len(self.robot.pose_joints)} finite joints and a finite '
                f'q_base'
            )
        # the estimator's own measurement model (MAP: errors in the measured pitch, not in x_com)
        if sigma is None:
            self.estimator.update(float(q_base), joints)
        else:
            self.estimator.update(float(q_base), joints, sigma=float(sigma))
        if in_motion:
            self.moving_points += 1
        else:
            self.poses.append((float(q_base), joints.copy()))
            self.history.append(self.estimator.beta)
        return self.estimator.beta

    def posterior(self):
        """(beta, covariance) now; the covariance is None for estimators without one."""
        return self.estimator.beta, self.estimator.covariance

    def com(self, q_base, joints):
        """The estimated CoM (frame 0) at a pose."""
        return com_frame0(
            self.robot, [q_base], np.asarray(joints, dtype=float)[None], self.estimator.beta
        )[0]

    def reset(self):
        self.__post_init__()
