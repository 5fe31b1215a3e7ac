"""Re-learn beta offline from the balanced poses recorded in a bag (today's BalancedPose and
MassModel, or the JointState and Float64MultiArray of older bags: krang_core.message_values)."""

from dataclasses import dataclass

import numpy as np

from krang_com_estimator.online import OnlineLearner
from krang_core.message_values import balanced_pose_values, mass_model_values
from krang_core.names import BALANCED_POSE as BALANCED_POSE_TOPIC, BETA as BETA_TOPIC

from .reader import iter_messages


@dataclass
class RelearnResult:
    beta0: np.ndarray
    betas: np.ndarray  # (n_poses + 1, n_beta): beta0 and after each pose at rest
    recorded: np.ndarray  # betas the online estimator published, in order
    poses: list  # (q_base, joints, sigma, in_motion) of every point learned
    beta: np.ndarray  # after every point (what the estimator's ~/save writes)

    @property
    def rest_poses(self):
        """The points at rest (one published beta each)."""
        return sum(1 for p in self.poses if not p[3])

    @property
    def max_deviation(self):
        """Largest |ours - online| over the betas published after each pose (nan if none
        recorded)."""
        n = min(len(self.recorded), len(self.betas))
        if n == 0:
            return float('nan')
        return float(np.abs(self.recorded[:n] - self.betas[:n]).max())

    @property
    def relative_deviation(self):
        """max_deviation over the largest |beta| element: the significant digits the replay
        shares."""
        return self.max_deviation / float(np.abs(self.betas).max())


def balanced_poses(bag, robot):
    """(q_base, joints, pitch standard error or None, read while moving) of every
    /balanced_pose message, in order; malformed ones are skipped."""
    poses = []
    for _, _, msg in iter_messages(bag, [BALANCED_POSE_TOPIC]):
        pose = balanced_pose_values(msg, robot.pose_joints)
        if pose is not None:
            poses.append((pose.q_base, pose.joints, pose.q_base_se, pose.in_motion))
    return poses


def recorded_betas(bag, robot):
    """The betas the online estimator published on /com_estimator/beta, in order."""
    betas = []
    for _, _, msg in iter_messages(bag, [BETA_TOPIC]):
        model = mass_model_values(msg, robot.n_beta)
        if model is not None:
            betas.append(model[0])
    return np.array(betas)


def relearn(bag, robot, method='map-online', beta0=None):
    recorded = recorded_betas(bag, robot)
    if beta0 is None:
        if len(recorded) == 0:
            raise ValueError(f'{bag}: no {BETA_TOPIC} message to start from; pass an initial beta')
        beta0 = recorded[0]
    learner = OnlineLearner(robot, beta0, method)
    poses = balanced_poses(bag, robot)
    for q_base, joints, sigma, in_motion in poses:
        learner.add_balanced_pose(q_base, joints, sigma, in_motion)
    return RelearnResult(
        np.asarray(beta0), np.array(learner.history), recorded, poses, learner.beta
    )
