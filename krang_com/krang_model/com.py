"""phi(q): the regressor of the mass-weighted CoM, and the CoM quantities built on it.

Frame 0 (paper §II): origin at the wheel-axle midpoint, x along the heading, z up. The base pitch
q_base is the IMU pitch of the hardware (krang_model/README.md, Conventions): the base frame is
placed by R0(q_base) = RotX(pi/2) RotY(-pi/2) RotX(-q_base), so in frame 0 a base-frame
vector (X, Y, Z) has x = sin(q_base) Y - cos(q_base) Z and z = cos(q_base) Y + sin(q_base) Z.

For body i with beta_i = [m, m c] (c in the body frame) the mass-weighted position in frame 0 is
m p_i + R_i (m c) = [p_i, R_i] beta_i, which is linear in beta. Stacking over bodies gives the
(3, 4B) regressor; its x row divided by the nominal total mass is the paper's phi(q).
"""

import numpy as np

from .kinematics import body_placements, projected_body_placements


def base_to_frame0(q_base):
    """Rotation (N, 3, 3) from the base frame to frame 0 for base pitches q_base (N,)."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    s, c = np.sin(q_base), np.cos(q_base)
    r = np.zeros((q_base.size, 3, 3))
    r[:, 0, 1], r[:, 0, 2] = s, -c
    r[:, 1, 0] = -1.0
    r[:, 2, 1], r[:, 2, 2] = c, s
    return r


def base_regressor(robot, joints):
    """(N, 3, 4B): sum_i m_i X_i in the BASE frame = base_regressor @ beta."""
    rot, trans = body_placements(robot, joints)
    n = rot.shape[0]
    reg = np.empty((n, 3, robot.n_bodies, 4))
    reg[..., 0] = trans.transpose(0, 2, 1)
    reg[..., 1:] = rot.transpose(0, 2, 1, 3)
    return reg.reshape(n, 3, robot.n_beta)


def regressor(robot, q_base, joints):
    """(N, 3, 4B): sum_i m_i X_i^0 in frame 0 = regressor @ beta (not normalised)."""
    return base_to_frame0(q_base) @ base_regressor(robot, joints)


def phi(robot, q_base, joints):
    """(N, 4B): the paper's phi(q) — x row of the regressor divided by the nominal total mass."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    # the x row of base_to_frame0 in base coordinates: (0, sin q_base, -cos q_base)
    x_row = np.column_stack([np.zeros_like(q_base), np.sin(q_base), -np.cos(q_base)])
    offset, row = projected_body_placements(robot, joints, x_row)
    n = q_base.size
    out = np.empty((n, robot.n_bodies, 4))
    out[..., 0] = offset
    out[..., 1:] = row
    return out.reshape(n, robot.n_beta) / robot.nominal_mass


def x_com(robot, q_base, joints, beta):
    """The paper's x_com = phi(q)^T beta (m): horizontal CoM offset times M(beta)/M_nominal."""
    return phi(robot, q_base, joints) @ np.asarray(beta, dtype=float)


def com_frame0(robot, q_base, joints, beta):
    """(N, 3) the true CoM in frame 0 (divided by beta's own total mass), wheels included."""
    beta = np.asarray(beta, dtype=float)
    return regressor(robot, q_base, joints) @ beta / beta[0::4].sum()


def base_moment_rows(robot, joints):
    """(Y, Z) (N, 4B) each: the base-frame y and z rows of the mass moment (rows 1 and 2 of
    base_regressor), from the y and z rows of the body frames alone
    (kinematics.projected_body_placements) at a fifth of the cost of the full regressor. They
    are all a balance pitch needs: x_com, the CoM height and phi follow from them at any pitch
    (PoseMoments)."""
    joints = np.atleast_2d(np.asarray(joints, dtype=float))
    n = joints.shape[0]
    directions = np.zeros((2 * n, 3))
    directions[:n, 1] = 1.0
    directions[n:, 2] = 1.0
    offset, row = projected_body_placements(robot, np.concatenate([joints, joints]), directions)
    rows = np.empty((2 * n, robot.n_bodies, 4))
    rows[..., 0] = offset
    rows[..., 1:] = row
    rows = rows.reshape(2 * n, robot.n_beta)
    return rows[:n], rows[n:]


def base_moment_yz(robot, joints, beta):
    """(Y, Z) (N,), (N,): the base-frame y and z of the mass moment of `beta`."""
    Y, Z = base_moment_rows(robot, joints)
    beta = np.asarray(beta, dtype=float)
    return Y @ beta, Z @ beta


def balance_pitch(robot, joints, beta):
    """q_base (N,) that puts the CoM of `beta` exactly over the axle with the CoM above it.

    x_com = sin(q) Y - cos(q) Z vanishes for q = atan2(Z, Y), where (Y, Z) are the base-frame y, z
    of the mass moment; that root has z_com = hypot(Y, Z) > 0 (the other root hangs below).
    """
    y, z = base_moment_yz(robot, joints, beta)
    return np.arctan2(z, y)


# ---- how wrong a beta is, against a known truth (simulation) ------------------------------------
def com_error(robot, beta, true_beta, joints):
    """Mean |x_com| (m, the paper's phi(q)^T beta) that `beta` predicts at the TRUE balance pitch
    of each pose (rows of `joints`): the forward CoM error, the one balancing observes; 0 for a
    perfect model."""
    joints = np.atleast_2d(np.asarray(joints, float))
    q_base = balance_pitch(robot, joints, true_beta)
    return float(np.mean(np.abs(x_com(robot, q_base, joints, beta))))


def lateral_com_error(robot, beta, true_beta, joints):
    """Mean sideways (frame-0 y) distance (m) between the CoM of `beta` and the true CoM, each pose
    at its true balance pitch. A robot balancing in pitch never observes it: learning leaves it at
    the prior."""
    joints = np.atleast_2d(np.asarray(joints, float))
    q_base = balance_pitch(robot, joints, true_beta)
    return float(
        np.mean(
            np.abs(
                com_frame0(robot, q_base, joints, beta)[:, 1]
                - com_frame0(robot, q_base, joints, true_beta)[:, 1]
            )
        )
    )


class PoseMoments:
    """The base-frame y and z rows of the mass moment (base_moment_rows) of a fixed set of
    configurations, to score many betas at once with one matrix product per set (the learning
    curves' hot path).

    Its balance error divides by each beta's own total mass (the horizontal CoM distance), where
    com_error gives the paper's x_com (divided by the nominal mass); both are the same for a beta
    of the nominal total mass."""

    def __init__(self, robot, joints):
        self.robot = robot
        self.Y, self.Z = base_moment_rows(robot, joints)  # (N, n_beta) each, base frame

    def balance(self, beta):
        """(q_base, phi, sensitivity) at each configuration for one beta: its balance pitch (N,),
        phi there (N, n_beta) and d(phi^T beta)/d q_base (N,) (krang_com_estimator.rows)."""
        beta = np.asarray(beta, dtype=float)
        y, z = self.Y @ beta, self.Z @ beta
        q = np.arctan2(z, y)
        phi, psi = self.phi_psi(self.Y, self.Z, q)
        return q, phi, psi @ beta

    def sequence_rows(self, index, betas):
        """For K runs, each with its own sequence of these configurations (index (K, L)): the
        mass-moment rows (Y, Z) (K, L, n_beta) and the balance pitch (K, L) of run k's beta."""
        Yk, Zk = self.Y[index], self.Z[index]
        q = np.arctan2(np.einsum('knj,kj->kn', Zk, betas), np.einsum('knj,kj->kn', Yk, betas))
        return Yk, Zk, q

    def phi_psi(self, Y, Z, q_base):
        """phi (the paper's, as phi()) and psi = d phi / d q_base from mass-moment rows Y, Z
        (..., n_beta) at the pitches q_base (...)."""
        s, c = np.sin(q_base)[..., None], np.cos(q_base)[..., None]
        m = self.robot.nominal_mass
        return (s * Y - c * Z) / m, (c * Y + s * Z) / m

    def errors(self, betas, true_betas):
        """betas, true_betas: (K, n_beta). Mean over the configurations of (balance, position)
        (K,) each, in metres: the horizontal CoM distance from the axle of beta k at the balance
        pitch of truth k, and the distance between the two CoMs in the sagittal plane (any pitch;
        it includes the scale of the moments, which balanced poses cannot observe)."""
        T = np.asarray(true_betas, dtype=float)
        B = np.asarray(betas, dtype=float)
        Yt, Zt = self.Y @ T.T, self.Z @ T.T
        Mt = T[:, 0::4].sum(1)
        q_true = np.arctan2(Zt, Yt)
        Ye, Ze = self.Y @ B.T, self.Z @ B.T
        Me = B[:, 0::4].sum(1)
        balance = np.abs(np.sin(q_true) * Ye - np.cos(q_true) * Ze) / Me
        position = np.hypot(Ye / Me - Yt / Mt, Ze / Me - Zt / Mt)
        return balance.mean(0), position.mean(0)
