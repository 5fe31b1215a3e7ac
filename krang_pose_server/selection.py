"""Adaptive choice of the next pose from what the estimator still does not know (plain numpy).

The estimator's posterior covariance Sigma of beta says how uncertain the forward CoM offset
x_com = phi(q)^T beta still is in every pose: var = phi^T Sigma phi. Learning from a candidate pose
c adds one row g_c (the CoM-angle row at the balance pitch the current estimate predicts; there
x_com = 0, so g_c = phi_c, krang_com_estimator.estimators.balanced_pose_rows) with noise variance
r_c = (sigma_pitch z_c)^2, z_c = psi_c^T beta the CoM height. The rank-one update lowers the
forward-error variance at every reference pose j by (phi_j^T Sigma g_c)^2 / (g_c^T Sigma g_c +
r_c), so the expected reduction of the mean squared forward error over the reference poses is

    gain_c = mean_j (phi_j^T Sigma g_c)^2 / (g_c^T Sigma g_c + r_c)        ('forward', default)

or, with criterion='d-optimal', the information gain log(1 + g_c^T Sigma g_c / r_c). The cost of
the move is its time at the pose server's joint speed (StraightLineMove, every joint arriving at
once) plus the settle time of a balanced point, and the chosen pose is the one with the most gain
per second: argmax gain_c / (settle_s + move_s_c). The reference poses are the pool itself (safe,
balanced poses stand for the poses the robot will use).
"""

from dataclasses import dataclass

import numpy as np

from krang_com_estimator.estimators import pitch_sensitivity
from krang_model.com import balance_pitch, phi as phi_fn

from .sequence import move_times

CRITERIA = ('forward', 'd-optimal')


@dataclass
class Choice:
    index: int  # into the pool
    joints: np.ndarray
    move_s: float
    gain: float  # expected reduction (m^2 for 'forward', nats for 'd-optimal')
    rms_before_m: float  # predicted RMS forward error over the reference poses
    rms_after_m: float  # ... after learning from this pose ('forward' gain only)


class AdaptiveSelector:
    """Chooses from a pool of safe, balanced poses (rows of joints, pose order)."""

    def __init__(
        self,
        robot,
        pool_joints,
        sigma_pitch_rad=np.radians(0.1),
        criterion='forward',
        settle_s=12.0,
        speed_fraction=0.8,
        reference_joints=None,
    ):
        if criterion not in CRITERIA:
            raise ValueError(f'criterion must be one of {CRITERIA}, not {criterion!r}')
        self.robot = robot
        self.pool = np.atleast_2d(np.asarray(pool_joints, dtype=float))
        self.reference = (
            self.pool
            if reference_joints is None
            else np.atleast_2d(np.asarray(reference_joints, dtype=float))
        )
        self.sigma_pitch = float(sigma_pitch_rad)
        self.criterion = criterion
        self.settle_s = float(settle_s)
        self.speed_fraction = float(speed_fraction)
        self.used = set()

    def reset(self):
        self.used.clear()

    def scores(self, beta, covariance, current_joints, sigma_pitch_rad=None):
        """(score, gain, move_s, rms_before, rms_after) over the pool; used poses score -inf."""
        beta = np.asarray(beta, dtype=float)
        cov = np.asarray(covariance, dtype=float)
        sigma = self.sigma_pitch if sigma_pitch_rad is None else float(sigma_pitch_rad)
        q = balance_pitch(self.robot, self.pool, beta)
        G = phi_fn(self.robot, q, self.pool)
        z = pitch_sensitivity(self.robot, q, self.pool, beta)
        r = (sigma * z) ** 2
        SG = cov @ G.T  # (n_beta, N)
        s = np.einsum('ij,ji->i', G, SG)  # g^T Sigma g
        if self.reference is self.pool:
            R = G
        else:
            R = phi_fn(self.robot, balance_pitch(self.robot, self.reference, beta), self.reference)
        before = float(np.mean(np.einsum('ij,ji->i', R, cov @ R.T)))
        if self.criterion == 'forward':
            gain = np.mean((R @ SG) ** 2, axis=0) / (s + r)
        else:
            gain = np.log1p(s / r)
        move = move_times(
            current_joints, self.pool, self.robot.velocity_limit, self.speed_fraction
        )
        score = gain / (self.settle_s + move)
        if self.used:
            score[list(self.used)] = -np.inf
        after = (
            np.sqrt(np.maximum(before - gain, 0.0))
            if self.criterion == 'forward'
            else np.full(len(gain), np.nan)
        )
        return score, gain, move, np.sqrt(before), after

    def choose(self, beta, covariance, current_joints, sigma_pitch_rad=None):
        """The next pose (a Choice), marked as used; None when the pool is used up."""
        if len(self.used) >= len(self.pool):
            return None
        score, gain, move, before, after = self.scores(
            beta, covariance, current_joints, sigma_pitch_rad
        )
        i = int(np.argmax(score))
        self.used.add(i)
        return Choice(
            i, self.pool[i].copy(), float(move[i]), float(gain[i]), float(before), float(after[i])
        )
