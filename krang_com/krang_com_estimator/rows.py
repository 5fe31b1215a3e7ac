"""The measurement model of a balanced pose: phi and psi rows, the noise, and the linear rows the
MAP solvers take (pure numpy).

At a balanced pose the whole-robot CoM is over the axle, so the paper's x_com = phi(q)^T beta (phi
divided by the nominal mass, krang_model.com.phi) is 0. What we observe is q_base from the IMU, off
by a pitch error dq (IMU noise, hand-balancing repeatability). Since
    phi(q)^T beta = (sin q Y - cos q Z) / M_nom   (Y, Z: base-frame mass moment, krang_model.com)
    psi(q)^T beta := d(phi^T beta)/dq_base = (cos q Y + sin q Z) / M_nom = M(beta)/M_nom *
    z_com(q),
a pitch error dq shows up as phi(q_meas)^T beta = z_com dq (+ O(dq^2)), z_com the CoM height above
the axle (frame 0): the x_com noise is sigma_pitch * z_com.

Balanced poses give only phi^T beta = 0, a homogeneous system: beta and c*beta fit equally well,
and the Base and wheel masses (phi = 0) can absorb any change of total mass, so even the known
total mass does not fix the scale of the mass moments (docs/learning.md, "What balanced poses can
and cannot tell"; identifiability.py). The scale comes from the prior. Worse, with a noisy pitch
the regressor itself is noisy (errors in variables): the paper's residual phi(q_meas)^T beta =
z_beta dq is smaller for a smaller beta, so least squares on it shrinks the whole moment vector,
and nothing in the data resists (docs/learning.md). The MAP estimators therefore use the
scale-free CoM angle at the measured pitch, h(beta) = phi^T beta / psi^T beta = tan(CoM angle from
vertical), with h(beta_true) = tan(-dq): linearised at beta_lin it is the linear row
g = phi - h_lin psi (g^T beta_lin = 0: no pull along the scale), and Gauss-Newton re-linearises
(balanced_pose_rows, solvers.map_gauss_newton).
"""

import math
from dataclasses import dataclass

import numpy as np

from krang_model.com import base_moment_rows, base_moment_yz, phi as phi_fn


def pitch_sensitivity(robot, q_base, joints, beta):
    """d(phi^T beta)/d q_base (N,) = M(beta)/M_nom * z_com: how a pitch error shows up in x_com
    (m/rad)."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    y, z = base_moment_yz(robot, joints, beta)  # base-frame mass moment
    return (np.cos(q_base) * y + np.sin(q_base) * z) / robot.nominal_mass


def pitch_rows(robot, q_base, joints):
    """psi(q) (N, n_beta) = d phi(q) / d q_base, so that psi^T beta = pitch_sensitivity."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    Y, Z = base_moment_rows(robot, joints)
    return (np.cos(q_base)[:, None] * Y + np.sin(q_base)[:, None] * Z) / robot.nominal_mass


def balanced_pose_rows(
    robot, q_meas, joints, beta_lin, noise=None, model='angle', sigma_pitch=None
):
    """Linear measurement rows of balanced poses for MAPEstimator / map_batch: (rows, y, var).

    model='angle' (default, one row per pose): the CoM angle at the measured pitch,
    h(beta) = phi^T beta / psi^T beta, linearised at beta_lin (x = phi^T beta_lin, z = psi^T
    beta_lin, h = x / z) and multiplied by z:   g^T beta = -x + z dq,   g = phi - h psi, var =
    (sigma_pitch z)^2 + sigma_x^2. g^T beta_lin = 0, so the rows carry no information along the
    scale of beta_lin, whatever the noise; the innovation g^T beta_lin - y = x is the paper's x_com
    error. model='phi': the paper's regression, row phi, y = 0, same variance (biased by the noisy
    pitch). model='eiv': 'phi' plus the first-order errors-in-variables correction, a second row
    psi with y = 0 and NEGATIVE variance -r/sigma^2 (removes the expected sigma^2 psi psi^T / r;
    corrected least squares); unbiased to first order only (second-order bias grows with the number
    of poses). sigma_pitch: per-pose standard errors of the pitch (rad; NaN = none), added in
    quadrature to the noise model's (NoiseModel.pitch_std)."""
    noise = noise or NoiseModel()
    q_meas = np.atleast_1d(np.asarray(q_meas, dtype=float))
    joints = np.atleast_2d(joints)
    P = phi_fn(robot, q_meas, joints)
    Psi = pitch_rows(robot, q_meas, joints)
    g, y, r = angle_rows(P, Psi, np.asarray(beta_lin, dtype=float), noise, sigma_pitch)
    if model == 'angle':
        return g, y, r
    if model == 'phi' or (model == 'eiv' and noise.sigma_pitch == 0):
        return P, np.zeros(len(P)), r
    if model != 'eiv':
        raise ValueError(f'model must be angle, phi or eiv, not {model!r}')
    n = len(P)
    rows = np.empty((2 * n, P.shape[1]))
    rows[0::2], rows[1::2] = P, Psi
    var = np.empty(2 * n)
    var[0::2], var[1::2] = r, -r / noise.pitch_std(sigma_pitch, n) ** 2
    return rows, np.zeros(2 * n), var


@dataclass(frozen=True)
class NoiseModel:
    """Noise of one balanced-pose measurement y = phi(q_meas)^T beta = 0.

    sigma_imu_rad: IMU pitch noise (0.1 deg by default); sigma_hand_rad: repeatability of finding
    the balance by hand (hardware: the cancelled attempts of the real-data kit scatter by ~9 mrad
    median); sigma_x_m: a floor for everything else (model error), in metres of x_com.
    """

    sigma_imu_rad: float = math.radians(0.1)
    sigma_hand_rad: float = 0.0
    sigma_x_m: float = 0.0

    @property
    def sigma_pitch(self):
        return math.hypot(self.sigma_imu_rad, self.sigma_hand_rad)

    def pitch_std(self, sigma_pitch=None, n=1):
        """(n,) pitch std of each pose: the model's sigma_pitch (what no single measurement
        reports: detector bias, model error) and, in quadrature, the pose's own standard error
        where one is given (finite), e.g. the detector's for its window mean."""
        if sigma_pitch is None:
            return np.full(n, self.sigma_pitch)
        s = np.broadcast_to(np.asarray(sigma_pitch, dtype=float), (n,))
        return np.hypot(self.sigma_pitch, np.where(np.isfinite(s), s, 0.0))

    def variance(self, robot, q_base, joints, beta_ref):
        """(N,) variance of y for each pose (z_com from the reference beta, e.g. the prior
        mean)."""
        dz = pitch_sensitivity(robot, q_base, joints, beta_ref)
        return (self.sigma_pitch * dz) ** 2 + self.sigma_x_m**2


def angle_rows(P, Psi, beta_lin, noise=None, sigma_pitch=None):
    """The 'angle' rows of balanced_pose_rows from precomputed phi (P) and psi (Psi) rows."""
    noise = noise or NoiseModel()
    x = P @ beta_lin
    z = Psi @ beta_lin
    s = noise.pitch_std(sigma_pitch, len(z))
    return P - (x / z)[:, None] * Psi, -x, (s * z) ** 2 + noise.sigma_x_m**2


def offset_rows(P, Psi, beta_lin, noise=None, sigma_pitch=None):
    """angle_rows with one more column for an IMU pitch offset b (q_meas = q_true + b + noise):
    the CoM angle at the measured pitch is then b + noise, so the row is [g, -z] (z = psi^T
    beta_lin), y = -x as before. The state is [beta, b]."""
    rows, y, var = angle_rows(P, Psi, beta_lin, noise, sigma_pitch)
    return np.column_stack([rows, -(Psi @ beta_lin)]), y, var
