"""Adaptive choice of the next pose from what the estimator still does not know (plain numpy).

The estimator's posterior covariance Sigma of beta says how uncertain the forward CoM offset
x_com = phi(q)^T beta still is in every pose: var = phi^T Sigma phi. Learning from a candidate pose
c adds one row g_c (the CoM-angle row at the balance pitch the current estimate predicts; there
x_com = 0, so g_c = phi_c, krang_com_estimator.rows.balanced_pose_rows) with noise variance
r_c = (sigma_pitch z_c)^2, z_c = psi_c^T beta the CoM height. The rank-one update lowers the
forward-error variance at every reference pose j by (phi_j^T Sigma g_c)^2 / (g_c^T Sigma g_c +
r_c), so the expected reduction of the mean squared forward error over the reference poses is

    gain_c = mean_j (phi_j^T Sigma g_c)^2 / (g_c^T Sigma g_c + r_c)        ('forward', default)

or, with criterion='d-optimal', the information gain log(1 + g_c^T Sigma g_c / r_c). The cost of
the move is its time at the pose server's joint speed (StraightLineMove, every joint arriving at
once) plus the settle time of a balanced point, and the chosen pose is the one with the most gain
per second: argmax gain_c / (settle_s + move_s_c). The time the pose server's pace adds where a
move sweeps the balance pitch fast (``sequence.MAX_BALANCE_RATE_RAD_S``) is not counted: the
moves that shift the CoM most are the informative ones, and a cost for that shift steered the
choice away from them (docs/learning.md). The reference poses are the pool itself (safe,
balanced poses stand for the poses the robot will use).

Caster margin. The pool is balanced under the nominal model, but the robot balances where the
truth puts it: with a real-sized CoM error a pose, or a pose on the way to it, can balance beyond
the caster (the controller then sits). So the choice keeps a margin for what the posterior does
not know: along the straight-line move (`path_points` poses), the balance pitch the current beta
predicts, less `margin_sigmas` of its posterior std (x_com there has variance g^T Sigma g and
moves by z per radian of pitch, so std = sqrt(g^T Sigma g) / z), must stay `caster_margin_rad`
above the caster pitch, or, where the robot already stands closer than that, never go lower
than where it starts. A candidate that breaks this is not chosen; when every one does, the one
whose path keeps the most margin is.

Path clearance. Both ends of a move are safe poses, but the straight joint line between them can
lower a gripper into the floor on the way (the full-body plant shows it: the controller then
saturates and the robot runs away). With ``path_check`` (``PosePool.path_clear``: collisions at
points along the line, at the balance pitch the current beta predicts), the best-scoring candidate
whose path is clear is chosen, and one whose path is not is refused.
"""

from dataclasses import dataclass

import numpy as np

from krang_model.com import PoseMoments
from krang_model.drivetrain import drivetrain

from .sequence import PATH_SEGMENTS, move_times, path_points

CRITERIA = ('forward', 'd-optimal')


@dataclass
class Choice:
    index: int  # into the pool
    joints: np.ndarray
    move_s: float
    gain: float  # expected reduction (m^2 for 'forward', nats for 'd-optimal')
    rms_before_m: float  # predicted RMS forward error over the reference poses
    rms_after_m: float  # ... after learning from this pose ('forward' gain only)
    margin_rad: float = np.nan  # lowest predicted pitch less its margin_sigmas std on the path,
    # above the caster pitch


def forward_gains(covariance, rows, reference, noise):
    """(gain, s) (N,), (N,): for each candidate row g_c with noise variance r_c, the expected
    reduction of the mean squared forward error over the reference rows (the module docstring's
    gain_c) and its prior variance s_c = g_c^T Sigma g_c."""
    sg = np.asarray(covariance, dtype=float) @ rows.T  # (n_beta, N)
    s = np.einsum('ij,ji->i', rows, sg)
    return np.mean((reference @ sg) ** 2, axis=0) / (s + noise), s


def predicted_pitch(robot, joints, beta, covariance):
    """(pitch, std) (N,), (N,): the balance pitch `beta` predicts at each pose (rows of joints) and
    its posterior std, sqrt(g^T Sigma g) / |z| (g = phi at that pitch, z = d x_com / d pitch)."""
    q, g, z = PoseMoments(robot, joints).balance(beta)
    var = np.einsum('ij,ij->i', g @ np.asarray(covariance, dtype=float), g)
    return q, np.sqrt(np.maximum(var, 0.0)) / np.abs(z)


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
        caster_margin_rad=0.1,
        margin_sigmas=2.0,
        path_points=PATH_SEGMENTS,
        caster_pitch=None,
        path_check=None,
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
        self.caster_margin = float(caster_margin_rad)
        self.margin_sigmas = float(margin_sigmas)
        self.path_points = max(1, int(path_points))
        self.caster_pitch = float(
            drivetrain(robot).caster_pitch if caster_pitch is None else caster_pitch
        )
        self.path_check = path_check  # (start, goal, beta) -> bool, or None: no check
        # the pool's mass-moment rows: every choice scores it for a new beta without kinematics
        self._pool_moments = PoseMoments(robot, self.pool)
        self._reference_moments = (
            None if reference_joints is None else PoseMoments(robot, self.reference)
        )
        self.used = set()
        self.refused = 0  # candidates refused by path_check

    def reset(self):
        self.used.clear()

    def path_margins(self, beta, covariance, current_joints):
        """(margin at the start, lowest margin on each candidate's path) (scalar, (N,)): the
        predicted balance pitch less margin_sigmas of its std, above the caster pitch, rad."""
        paths = path_points(current_joints, self.pool, self.path_points)  # (P + 1, N, n_joints)
        q, sd = predicted_pitch(
            self.robot, paths.reshape(-1, self.pool.shape[1]), beta, covariance
        )
        lower = (q - self.margin_sigmas * sd - self.caster_pitch).reshape(len(paths), -1)
        return float(lower[0, 0]), lower[1:].min(axis=0)

    def scores(self, beta, covariance, current_joints, sigma_pitch_rad=None):
        """(score, gain, move_s, rms_before, rms_after, path margin) over the pool; used poses,
        and poses whose path breaks the caster margin while others keep it, score -inf."""
        beta = np.asarray(beta, dtype=float)
        cov = np.asarray(covariance, dtype=float)
        sigma = self.sigma_pitch if sigma_pitch_rad is None else float(sigma_pitch_rad)
        q, G, z = self._pool_moments.balance(beta)
        r = (sigma * z) ** 2
        R = G if self._reference_moments is None else self._reference_moments.balance(beta)[1]
        before = float(np.mean(np.einsum('ij,ji->i', R, cov @ R.T)))
        gain, s = forward_gains(cov, G, R, r)
        if self.criterion != 'forward':
            gain = np.log1p(s / r)
        move = move_times(
            current_joints, self.pool, self.robot.velocity_limit, self.speed_fraction
        )
        score = gain / (self.settle_s + move)
        start, margin = self.path_margins(beta, cov, current_joints)
        safe = margin >= min(self.caster_margin, start)
        if self.used:
            safe[list(self.used)] = False
        if safe.any():
            score[~safe] = -np.inf
        else:  # every path breaks the margin: the one that keeps the most
            score = margin.copy()
        if self.used:
            score[list(self.used)] = -np.inf
        after = (
            np.sqrt(np.maximum(before - gain, 0.0))
            if self.criterion == 'forward'
            else np.full(len(gain), np.nan)
        )
        return score, gain, move, np.sqrt(before), after, margin

    def choose(self, beta, covariance, current_joints, sigma_pitch_rad=None):
        """The next pose (a Choice), marked as used; None when the pool is used up."""
        if len(self.used) >= len(self.pool):
            return None
        score, gain, move, before, after, margin = self.scores(
            beta, covariance, current_joints, sigma_pitch_rad
        )
        i = self._first_clear(score, beta, current_joints)
        if i is None:
            return None
        self.used.add(i)
        return Choice(
            i,
            self.pool[i].copy(),
            float(move[i]),
            float(gain[i]),
            float(before),
            float(after[i]),
            float(margin[i]),
        )

    def _first_clear(self, score, beta, current_joints):
        """The best-scoring candidate whose path passes ``path_check`` (None if none does)."""
        if self.path_check is None:
            return int(np.argmax(score))
        for i in np.argsort(-score, kind='stable'):
            if score[i] == -np.inf:  # used, or its path breaks the caster margin
                break
            if self.path_check(current_joints, self.pool[i], beta):
                return int(i)
            self.refused += 1
        return None
