"""Estimators of the mass model beta from balanced poses (pure numpy; no rclpy).

Measurement model. At a balanced pose the whole-robot CoM is over the axle, so the paper's
x_com = phi(q)^T beta (phi divided by the nominal mass, krang_model.com.phi) is 0. What we observe
is q_base from the IMU, off by a pitch error dq (IMU noise, hand-balancing repeatability). Since
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
and nothing in the data resists (-8 cm of CoM height after 400 noisy poses, docs/learning.md). The
MAP estimator therefore uses the scale-free CoM angle at the measured pitch, h(beta) = phi^T beta
/ psi^T beta = tan(CoM angle from vertical), with h(beta_true) = tan(-dq): linearised at beta_lin
it is the linear row g = phi - h_lin psi (g^T beta_lin = 0: no pull along the scale), and Gauss-
Newton re-linearises (balanced_pose_rows, map_gauss_newton).

Estimators: one registry (ESTIMATORS, filled by @register_estimator; make_estimator(name, robot,
beta0, **options)) and one protocol (Estimator: `update(q_base, joints)` learns from one balanced
pose with the estimator's own measurement model and returns the paper's x_com error before the
update; `beta`, `covariance`, `n_updates`, `reset(beta0=None)`, and the batch `fit(q_base,
joints)`; `update` also takes an optional `sigma`, the pose's pitch std in rad):
- `paper-gd`: the paper's GD, beta <- beta - eta (phi^T beta - y) phi (eta = 300), with the stop
  rule
  |phi^T beta| < x_tol for the last `window` poses, and the authors' unused mass penalty u.
- `paper-gd-mass`: the same step followed by the Lagrange-multiplier projection that keeps the
  total
  mass at M_known (the constraint the paper describes and the authors left off).
- `map-online` / `map`: Bayesian MAP with a Gaussian prior N(beta0, diag(s^2)) from physical
  plausibility and hard linear equality constraints (known total mass, wheel CoMs on the axle)
  imposed by conditioning the prior on them. `MAPEstimator` is the linear-Gaussian core: a Kalman
  / recursive least-squares rank-one update of (mean, covariance) from given rows; `map_batch`
  solves the same problem in one go (null-space form) with the same result. `MAPOnline` feeds it
  the CoM-angle rows and re-linearises (a batch Gauss-Newton pass over the poses so far) when the
  estimate has moved enough to matter; `map_gauss_newton` is the batch form, which `MAP.fit` uses
  and `MAPOnline.finalize()` equals.
The paper estimators and MAPEstimator also take linear rows (`update_row`, `update_rows`).
`map_constrained` adds the inequality constraints of physical consistency (positive masses, every
CoM inside the inflated collision box of its link) as a QP, used when the Gaussian MAP violates
them.
"""

import importlib.metadata
import inspect
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve
from scipy.optimize import minimize

from krang_model.com import base_regressor, phi as phi_fn


# ---------------------------------------------------------------- measurement model
def pitch_sensitivity(robot, q_base, joints, beta):
    """d(phi^T beta)/d q_base (N,) = M(beta)/M_nom * z_com: how a pitch error shows up in x_com
    (m/rad)."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    base = base_regressor(robot, joints) @ np.asarray(
        beta, dtype=float
    )  # (N, 3) base-frame moment
    return (np.cos(q_base) * base[:, 1] + np.sin(q_base) * base[:, 2]) / robot.nominal_mass


def pitch_rows(robot, q_base, joints):
    """psi(q) (N, n_beta) = d phi(q) / d q_base, so that psi^T beta = pitch_sensitivity."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    base = base_regressor(robot, joints)
    return (
        np.cos(q_base)[:, None] * base[:, 1] + np.sin(q_base)[:, None] * base[:, 2]
    ) / robot.nominal_mass


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
    beta_lin = np.asarray(beta_lin, dtype=float)
    x = P @ beta_lin
    z = Psi @ beta_lin
    r = (noise.pitch_std(sigma_pitch, len(z)) * z) ** 2 + noise.sigma_x_m**2
    if model == 'angle':
        return P - (x / z)[:, None] * Psi, -x, r
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


# ---------------------------------------------------------------- priors and physical constraints
def physical_prior_std(robot, beta0=None, mass_frac=0.1, com_std=0.03, mass_floor=1e-3):
    """Prior std per beta entry from physical plausibility: each mass known to `mass_frac`
    (relative, at least `mass_floor` kg), each CoM coordinate to `com_std` metres. For the moment
    m*c with m and c independent: var(m c) = (m s_c)^2 + (c s_m)^2 + (s_m s_c)^2."""
    beta0 = robot.nominal_beta if beta0 is None else np.asarray(beta0, dtype=float)
    std = np.empty_like(beta0)
    for i in range(robot.n_bodies):
        m = beta0[4 * i]
        c = beta0[4 * i + 1 : 4 * i + 4] / m if m != 0 else np.zeros(3)
        s_m = max(mass_frac * abs(m), mass_floor)
        std[4 * i] = s_m
        std[4 * i + 1 : 4 * i + 4] = np.sqrt(
            (m * com_std) ** 2 + (c * s_m) ** 2 + (s_m * com_std) ** 2
        )
    return std


def recipe_prior_std(beta0, max_deviation=0.5, max_offset=0.5, mass_std=1e-6):
    """Prior std matching the authors' erroneous-beta recipe (masses exact; v + U(-d,d) v +
    U(-o,o)): var = (d^2 v^2 + o^2) / 3 per moment entry, with v taken as the start value."""
    beta0 = np.asarray(beta0, dtype=float)
    std = np.sqrt((max_deviation**2 * beta0**2 + max_offset**2) / 3.0)
    std[0::4] = mass_std
    return std


def equality_constraints(robot, total_mass=None, wheels_on_axle=True):
    """(A, b) of the hard linear constraints A beta = b: sum of masses = total_mass (if given) and
    each wheel's m*y = m*z = 0 (its CoM on its own axis, which is the axle; the wheel frame's x
    axis is the axle)."""
    rows, rhs = [], []
    if total_mass is not None:
        a = np.zeros(robot.n_beta)
        a[0::4] = 1.0
        rows.append(a)
        rhs.append(float(total_mass))
    if wheels_on_axle:
        for w in robot.wheel_body_ids:
            for k in (2, 3):
                a = np.zeros(robot.n_beta)
                a[4 * w + k] = 1.0
                rows.append(a)
                rhs.append(0.0)
    if not rows:
        return np.zeros((0, robot.n_beta)), np.zeros(0)
    return np.array(rows), np.array(rhs)


def com_bounds(robot, inflate=0.05):
    """Plausible CoM region of every body, in its own frame: the axis-aligned bounding box of its
    URDF collision shape grown by `inflate` metres on every side, and always containing the CAD CoM
    (grown likewise). Bodies without collision geometry (the gripper plates) get the box of
    `inflate` around the CAD CoM. Returns (lo, hi) arrays (n_bodies, 3)."""
    root = ET.parse(robot.urdf_path).getroot()
    lo = np.empty((robot.n_bodies, 3))
    hi = np.empty((robot.n_bodies, 3))
    beta0 = robot.nominal_beta
    for i, name in enumerate(robot.body_names):
        cad = beta0[4 * i + 1 : 4 * i + 4] / beta0[4 * i]
        box_lo, box_hi = cad.copy(), cad.copy()
        for col in root.findall(f"link[@name='{name}']/collision"):
            corners = _shape_corners(col)
            if corners is not None:
                box_lo = np.minimum(box_lo, corners.min(0))
                box_hi = np.maximum(box_hi, corners.max(0))
        lo[i], hi[i] = box_lo - inflate, box_hi + inflate
    return lo, hi


def _shape_corners(col):
    origin = col.find('origin')
    xyz = (
        np.zeros(3)
        if origin is None
        else np.array([float(v) for v in origin.get('xyz', '0 0 0').split()])
    )
    rpy = (
        np.zeros(3)
        if origin is None
        else np.array([float(v) for v in origin.get('rpy', '0 0 0').split()])
    )
    geom = col.find('geometry')
    if geom.find('box') is not None:
        half = np.array([float(v) for v in geom.find('box').get('size').split()]) / 2
    elif geom.find('cylinder') is not None:
        r = float(geom.find('cylinder').get('radius'))
        half = np.array([r, r, float(geom.find('cylinder').get('length')) / 2])
    elif geom.find('sphere') is not None:
        half = np.full(3, float(geom.find('sphere').get('radius')))
    else:
        return None
    signs = np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float
    )
    return xyz + (signs * half) @ _rpy(rpy).T


def _rpy(rpy):
    r, p, y = rpy
    cx, sx, cy, sy, cz, sz = (
        math.cos(r),
        math.sin(r),
        math.cos(p),
        math.sin(p),
        math.cos(y),
        math.sin(y),
    )
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def inequality_constraints(robot, bounds=None, min_mass=0.0):
    """(G, h) with G beta >= h: every mass >= min_mass and every CoM coordinate inside its bounds,
    written linearly as m*c - lo*m >= 0 and hi*m - m*c >= 0."""
    lo, hi = com_bounds(robot) if bounds is None else bounds
    rows, rhs = [], []
    for i in range(robot.n_bodies):
        a = np.zeros(robot.n_beta)
        a[4 * i] = 1.0
        rows.append(a)
        rhs.append(min_mass)
        for k in range(3):
            a = np.zeros(robot.n_beta)
            a[4 * i + 1 + k], a[4 * i] = 1.0, -lo[i, k]
            rows.append(a)
            rhs.append(0.0)
            a = np.zeros(robot.n_beta)
            a[4 * i + 1 + k], a[4 * i] = -1.0, hi[i, k]
            rows.append(a)
            rhs.append(0.0)
    return np.array(rows), np.array(rhs)


def physical_consistency(robot, beta, total_mass=None, bounds=None, tol=1e-6):
    """Checks a beta for physical consistency. Returns a dict: ok, and the list of violations
    (negative masses, total mass off, CoMs outside their bounds, wheel CoMs off the axle), plus the
    CoM of every body and its distance from the CAD CoM."""
    beta = np.asarray(beta, dtype=float)
    lo, hi = com_bounds(robot) if bounds is None else bounds
    total_mass = robot.nominal_mass if total_mass is None else total_mass
    violations = []
    bodies = []
    cad = robot.nominal_beta
    for i, name in enumerate(robot.body_names):
        m = beta[4 * i]
        com = beta[4 * i + 1 : 4 * i + 4] / m if m != 0 else np.full(3, np.nan)
        com_cad = cad[4 * i + 1 : 4 * i + 4] / cad[4 * i]
        moved = float(np.linalg.norm(com - com_cad))
        bodies.append(
            {
                'name': name,
                'mass': float(m),
                'com': com.tolist(),
                'com_moved_m': moved,
                'mass_change_kg': float(m - cad[4 * i]),
            }
        )
        if not m > 0:
            violations.append(f'{name}: mass {m:.4g} kg is not positive')
            continue
        out = (com < lo[i] - tol) | (com > hi[i] + tol)
        if out.any():
            violations.append(
                f'{name}: CoM {np.round(com, 4).tolist()} m outside its plausible box '
                f'[{np.round(lo[i], 3).tolist()}, {np.round(hi[i], 3).tolist()}]'
            )
    for w in robot.wheel_body_ids:
        off = np.abs(beta[4 * w + 2 : 4 * w + 4])
        if off.max() > tol:
            violations.append(
                f'{robot.body_names[w]}: CoM off the axle (m*y, m*z = '
                f'{beta[4 * w + 2]:.3g}, {beta[4 * w + 3]:.3g} kg m)'
            )
    mass = float(beta[0::4].sum())
    if abs(mass - total_mass) > 1e-6 * total_mass:
        violations.append(f'total mass {mass:.3f} kg instead of {total_mass:.3f} kg')
    return {'ok': not violations, 'violations': violations, 'total_mass': mass, 'bodies': bodies}


def com_shift_std(robot, beta, covariance, reference=None):
    """Posterior std (m) of how far each body's CoM moved from `reference` (default CAD), by the
    delta method: c = (m c)/m, J = [-(m c)/m^2, I/m], var(c) = J Sigma_body J^T, projected on the
    direction of the shift (the whole 3-d std where the CoM did not move). (n_bodies,) array."""
    beta = np.asarray(beta, dtype=float)
    ref = robot.nominal_beta if reference is None else np.asarray(reference, dtype=float)
    out = np.empty(robot.n_bodies)
    for i in range(robot.n_bodies):
        m, mc = beta[4 * i], beta[4 * i + 1 : 4 * i + 4]
        J = np.column_stack([-mc / m**2, np.eye(3) / m])
        cov = J @ covariance[4 * i : 4 * i + 4, 4 * i : 4 * i + 4] @ J.T
        d = mc / m - ref[4 * i + 1 : 4 * i + 4] / ref[4 * i]
        norm = np.linalg.norm(d)
        out[i] = (
            math.sqrt(max(d @ cov @ d / norm**2, 0.0))
            if norm > 1e-9
            else math.sqrt(max(np.trace(cov), 0.0))
        )
    return out


# ---------------------------------------------------------------- linear MAP, batch forms
def condition_on_constraints(mean, cov, A, b):
    """Gaussian N(mean, cov) conditioned on A beta = b (noise-free linear observations)."""
    S = A @ cov @ A.T
    K = np.linalg.solve(S, A @ cov).T
    mean = mean + K @ (b - A @ mean)
    cov = cov - K @ A @ cov
    return mean, 0.5 * (cov + cov.T)


def null_space(A, n):
    """Orthonormal basis Z (n, n - rank A) of {v : A v = 0}."""
    if len(A) == 0:
        return np.eye(n)
    _, s, vt = np.linalg.svd(A)
    rank = int((s > 1e-12 * s.max()).sum())
    return vt[rank:].T


def map_batch(beta0, prior_std, phi_rows, y=None, noise_var=1e-6, A=None, b=None, covariance=True):
    """The MAP estimate and posterior covariance in one solve (information / null-space form):
        minimise (beta-beta0)^T P0^-1 (beta-beta0) + sum_i (y_i - phi_i^T beta)^2 / r_i  s.t. A
        beta = b.
    With beta = beta_p + Z z (A beta_p = b, A Z = 0): H_z = Z^T (P0^-1 + Phi^T R^-1 Phi) Z,
    z = H_z^-1 Z^T (P0^-1 (beta0 - beta_p) + Phi^T R^-1 (y - Phi beta_p)), Sigma = Z H_z^-1 Z^T.
    covariance=False skips Sigma (returns None)."""
    beta0 = np.asarray(beta0, dtype=float)
    n = len(beta0)
    Phi = np.atleast_2d(np.asarray(phi_rows, dtype=float)).reshape(-1, n)
    y = np.zeros(len(Phi)) if y is None else np.asarray(y, dtype=float)
    r = np.broadcast_to(np.asarray(noise_var, dtype=float), (len(Phi),))
    p0inv = 1.0 / np.asarray(prior_std, dtype=float) ** 2
    A = np.zeros((0, n)) if A is None else np.atleast_2d(A)
    b = np.zeros(0) if b is None else np.atleast_1d(b)
    beta_p, Z = _constraint_basis(A, b, n)
    PZ = Phi @ Z
    WZ = PZ / r[:, None]
    Hz = _prior_information(p0inv, Z) + PZ.T @ WZ
    g = Z.T @ (p0inv * (beta0 - beta_p)) + WZ.T @ (y - Phi @ beta_p)
    Hz = 0.5 * (Hz + Hz.T)
    try:
        L = np.linalg.cholesky(Hz)
    except np.linalg.LinAlgError:
        raise np.linalg.LinAlgError(
            'map_batch: the posterior information is not positive definite (negative-'
            'variance rows removed more information than the prior and data hold)'
        ) from None
    z = _chol_solve(L, g)
    beta = beta_p + Z @ z
    if not covariance:
        return beta, None
    Li = np.linalg.solve(L, Z.T)
    cov = Li.T @ Li
    return beta, cov


def _prior_information(p0inv, Z):
    key = (p0inv.tobytes(), Z.shape)
    hit = _BASIS_CACHE.get(key)
    if hit is None or hit[0] is not Z:
        hit = (Z, (Z.T * p0inv) @ Z)
        _BASIS_CACHE[key] = hit
    return hit[1]


def _chol_solve(L, g):
    return cho_solve((L, True), g)


_BASIS_CACHE = {}


def _constraint_basis(A, b, n):
    """(beta_p, Z): a particular solution of A beta = b and an orthonormal basis of the null space
    of A."""
    key = (A.tobytes(), b.tobytes(), n)
    hit = _BASIS_CACHE.get(key)
    if hit is None:
        beta_p = np.linalg.lstsq(A, b, rcond=None)[0] if len(A) else np.zeros(n)
        hit = (beta_p, null_space(A, n))
        if len(_BASIS_CACHE) > 64:
            _BASIS_CACHE.clear()
        _BASIS_CACHE[key] = hit
    return hit


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


def map_gauss_newton(
    robot,
    q_meas,
    joints,
    beta0,
    prior_std,
    noise=None,
    A=None,
    b=None,
    iterations=20,
    tol=1e-10,
    beta_start=None,
    sigma_pitch=None,
    pitch_offset_std=None,
):
    """Batch MAP of the CoM-angle model by Gauss-Newton: linearise every pose at the current
    iterate (start: beta_start or the prior mean), solve the linear MAP, repeat until the step is
    below tol (relative to |beta0|). Returns (beta, covariance, beta_lin), beta_lin being the
    linearisation point of the last solve (= beta at convergence). sigma_pitch: per-pose pitch std
    (rad). pitch_offset_std: also estimate an IMU pitch offset b with prior N(0,
    pitch_offset_std^2) (offset_rows); beta, covariance and beta_lin then have one more entry, b,
    last."""
    q_meas = np.atleast_1d(np.asarray(q_meas, dtype=float))
    joints = np.atleast_2d(joints)
    return map_gauss_newton_rows(
        phi_fn(robot, q_meas, joints),
        pitch_rows(robot, q_meas, joints),
        beta0,
        prior_std,
        noise,
        A,
        b,
        iterations,
        tol,
        beta_start,
        sigma_pitch=sigma_pitch,
        pitch_offset_std=pitch_offset_std,
    )


def map_gauss_newton_rows(
    P,
    Psi,
    beta0,
    prior_std,
    noise=None,
    A=None,
    b=None,
    iterations=20,
    tol=1e-10,
    beta_start=None,
    covariance=True,
    sigma_pitch=None,
    pitch_offset_std=None,
):
    """map_gauss_newton from precomputed phi and psi rows of the poses (measured pitch)."""
    beta0, prior_std, A, b, rows_fn = _with_offset(beta0, prior_std, A, b, pitch_offset_std)
    n = P.shape[1]
    lin = beta0.copy() if beta_start is None else np.asarray(beta_start, dtype=float).copy()
    if len(lin) < len(beta0):
        lin = np.append(lin, 0.0)
    scale = np.abs(beta0).max()
    for it in range(max(1, iterations)):
        rows, y, var = rows_fn(P, Psi, lin[:n], noise, sigma_pitch)
        beta, _ = map_batch(beta0, prior_std, rows, y, var, A, b, covariance=False)
        if np.abs(beta - lin).max() < tol * scale or it == iterations - 1:
            break
        lin = beta
    beta, cov = map_batch(beta0, prior_std, rows, y, var, A, b, covariance=covariance)
    return beta, cov, lin


def _with_offset(beta0, prior_std, A, b, pitch_offset_std):
    """(beta0, prior_std, A, b, rows function) of the state [beta] or [beta, pitch offset]."""
    beta0 = np.asarray(beta0, dtype=float)
    if pitch_offset_std is None:
        return beta0, prior_std, A, b, angle_rows
    n = len(beta0)
    A = np.zeros((0, n)) if A is None else np.atleast_2d(A)
    return (
        np.append(beta0, 0.0),
        np.append(prior_std, float(pitch_offset_std)),
        np.column_stack([A, np.zeros(len(A))]),
        b,
        offset_rows,
    )


def log_evidence(
    P,
    Psi,
    beta_lin,
    beta0,
    prior_std,
    noise=None,
    A=None,
    b=None,
    sigma_pitch=None,
    pitch_offset_std=None,
):
    """log p(data | noise, prior) of the angle model linearised at beta_lin (its MAP, for the
    Laplace-style evidence used by calibrate_scales): y ~ N(G mu0, G S0 G^T + R), mu0, S0 the
    prior conditioned on A beta = b."""
    beta0, prior_std, A, b, rows_fn = _with_offset(beta0, prior_std, A, b, pitch_offset_std)
    mu, S = np.asarray(beta0, float), np.diag(np.asarray(prior_std, float) ** 2)
    if A is not None and len(A):
        mu, S = condition_on_constraints(mu, S, A, b)
    G, y, var = rows_fn(P, Psi, np.asarray(beta_lin, float)[: P.shape[1]], noise, sigma_pitch)
    C = G @ S @ G.T + np.diag(var)
    L = np.linalg.cholesky(0.5 * (C + C.T))
    d = np.linalg.solve(L, y - G @ mu)
    return float(-0.5 * d @ d - np.log(np.diag(L)).sum() - 0.5 * len(y) * math.log(2 * math.pi))


#: plausibility bounds of calibrate_scales: pitch noise (rad), relative mass std, CoM std (m)
CALIBRATION_BOUNDS = {
    'sigma_pitch_rad': (1e-4, 0.05),
    'mass_frac': (0.01, 0.5),
    'com_std_m': (0.002, 0.1),
}


def calibrate_scales(
    robot,
    q_meas,
    joints,
    beta0,
    A=None,
    b=None,
    start=None,
    sigma_pitch=None,
    pitch_offset_std=None,
    rounds=3,
):
    """Noise and prior scales from the data by evidence maximisation (type-II maximum
    likelihood): the pitch noise sigma_pitch and the prior's mass_frac and com_std
    (physical_prior_std) that maximise log_evidence, alternating with the Gauss-Newton MAP they
    give (the linearisation point), within CALIBRATION_BOUNDS. Per-pose sigma_pitch values, if
    given, are added in quadrature (NoiseModel.pitch_std). Returns a dict (sigma_pitch_rad,
    mass_frac, com_std_m, log_evidence)."""
    q_meas = np.atleast_1d(np.asarray(q_meas, dtype=float))
    joints = np.atleast_2d(joints)
    P, Psi = phi_fn(robot, q_meas, joints), pitch_rows(robot, q_meas, joints)
    start = start or {'sigma_pitch_rad': math.radians(0.1), 'mass_frac': 0.1, 'com_std_m': 0.03}
    keys = ('sigma_pitch_rad', 'mass_frac', 'com_std_m')
    bounds = [tuple(np.log(CALIBRATION_BOUNDS[k])) for k in keys]
    theta = np.log([start[k] for k in keys])

    def unpack(t):
        s, mf, cs = np.exp(t)
        std = physical_prior_std(robot, beta0, mass_frac=mf, com_std=cs)
        return NoiseModel(sigma_imu_rad=s), sigma_pitch, std

    def fit(t):
        noise, sp, std = unpack(t)
        return map_gauss_newton_rows(
            P,
            Psi,
            beta0,
            std,
            noise,
            A,
            b,
            sigma_pitch=sp,
            pitch_offset_std=pitch_offset_std,
            covariance=False,
        )[0]

    def cost(t, lin):
        noise, sp, std = unpack(t)
        return -log_evidence(P, Psi, lin, beta0, std, noise, A, b, sp, pitch_offset_std)

    lin = fit(theta)
    best = None
    for _ in range(rounds):
        res = minimize(cost, theta, args=(lin,), method='L-BFGS-B', bounds=bounds)
        theta = res.x
        lin = fit(theta)
        if best is not None and abs(best - res.fun) < 1e-3:
            break
        best = res.fun
    out = dict(zip(keys, (float(v) for v in np.exp(theta))))
    out['log_evidence'] = -cost(theta, lin)
    return out


def map_constrained(
    beta0,
    prior_std,
    phi_rows,
    y=None,
    noise_var=1e-6,
    A=None,
    b=None,
    G=None,
    h=None,
    beta_start=None,
):
    """MAP with the equality constraints A beta = b AND the inequalities G beta >= h (a convex QP;
    solved on the null space of A by scipy's SLSQP with exact gradients). Returns beta."""
    beta0 = np.asarray(beta0, dtype=float)
    n = len(beta0)
    Phi = np.atleast_2d(np.asarray(phi_rows, dtype=float)).reshape(-1, n)
    y = np.zeros(len(Phi)) if y is None else np.asarray(y, dtype=float)
    r = np.broadcast_to(np.asarray(noise_var, dtype=float), (len(Phi),))
    A = np.zeros((0, n)) if A is None else np.atleast_2d(A)
    b = np.zeros(0) if b is None else np.atleast_1d(b)
    start, _ = (
        map_batch(beta0, prior_std, Phi, y, r, A, b) if beta_start is None else (beta_start, None)
    )
    if G is None or np.all(G @ start >= h - 1e-12):
        return start
    Z = null_space(A, n)
    p0inv = 1.0 / np.asarray(prior_std, dtype=float) ** 2
    W = Phi / r[:, None]
    H = Z.T @ (np.diag(p0inv) + Phi.T @ W) @ Z
    g = Z.T @ (p0inv * (beta0 - start) + W.T @ (y - Phi @ start))
    # in z: f(z) = 1/2 z^T H z - g^T z ; beta = start + Z z ; constraint G Z z >= h - G start
    scale = max(float(np.abs(np.diag(H)).max()), 1.0)
    Hs, gs = H / scale, g / scale
    GZ, hz = G @ Z, h - G @ start
    res = minimize(
        lambda z: 0.5 * z @ Hs @ z - gs @ z,
        np.zeros(Z.shape[1]),
        jac=lambda z: Hs @ z - gs,
        constraints=[{'type': 'ineq', 'fun': lambda z: GZ @ z - hz, 'jac': lambda z: GZ}],
        method='SLSQP',
        options={'maxiter': 500, 'ftol': 1e-14},
    )
    beta = start + Z @ res.x
    return beta


# ---------------------------------------------------------------- the estimator registry
#: name -> Estimator subclass; filled by @register_estimator (built-ins, plug-ins)
ESTIMATORS = {}
ENTRY_POINT_GROUP = 'krang_com.estimators'
_plugins_loaded = False


def register_estimator(name):
    """Class decorator: make an Estimator subclass available by `name` to make_estimator, and so to
    the com_estimator node's `method` parameter, `krang learn/relearn --method`, the closed loop
    and the experiments. Register your own the same way, in a module imported before the CLI is
    built or named in the `krang_com.estimators` entry-point group of your package."""

    def add(cls):
        if ESTIMATORS.get(name, cls) is not cls:
            raise ValueError(
                f'estimator {name!r} is already registered ({ESTIMATORS[name].__name__})'
            )
        cls.name = name
        ESTIMATORS[name] = cls
        return cls

    return add


def _load_plugins():
    """Import the modules of the entry-point group once (each registers its estimators)."""
    global _plugins_loaded
    if not _plugins_loaded:
        _plugins_loaded = True
        for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
            ep.load()


def estimator_names():
    """The registered names, built-in ones first (the CLI's --method choices)."""
    _load_plugins()
    return tuple(ESTIMATORS)


def make_estimator(name, robot, beta0, **options):
    """A registered estimator: ESTIMATORS[name](robot, beta0, **options). Options its constructor
    does not take are dropped (unless it takes **kwargs), so one set of options, e.g. the CLI's,
    serves every method."""
    _load_plugins()
    if name not in ESTIMATORS:
        raise ValueError(f'unknown estimator {name!r}; choose one of {tuple(ESTIMATORS)}')
    cls = ESTIMATORS[name]
    params = inspect.signature(cls).parameters
    if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
        options = {k: v for k, v in options.items() if k in params}
    return cls(robot, beta0, **options)


class Estimator:
    """The update protocol of every registered estimator.

    `cls(robot, beta0, **options)`; `update(q_base, joints)` learns from one balanced pose
    (measured base pitch in rad, joints in pose order) with the estimator's own measurement model
    and returns the paper's x_com error before the update; `beta`, `covariance` (None if it has
    none), `n_updates`, `errors` (x_com error before each update); `reset(beta0=None)` starts over
    (from a new beta0 if given; options derived from beta0 at construction are kept); `fit(q_base,
    joints)` learns from a batch and returns (beta, info): by default one update per pose in the
    given order, overridden where a closed form exists (map)."""

    name = 'estimator'

    def __init__(self, robot, beta0):
        self.robot = robot
        self.beta0 = np.array(beta0, dtype=float)
        self.reset()

    def reset(self, beta0=None):
        if beta0 is not None:
            self.beta0 = np.array(beta0, dtype=float)
        self._beta = self.beta0.copy()
        self.n_updates = 0
        self.errors = []

    @property
    def beta(self):
        return self._beta.copy()

    @property
    def covariance(self):
        return None

    def update(self, q_base, joints, sigma=None):
        """Learn from one balanced pose; `sigma` (optional): the pose's own pitch standard error
        in rad (the detector's), which estimators with a noise model add to it for this pose."""
        raise NotImplementedError

    def fit(self, q_base, joints):
        """Learn from the poses (rows of joints, measured q_base), from beta0: (beta, info)."""
        q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
        joints = np.atleast_2d(joints)
        self.reset()
        for qb, jt in zip(q_base, joints):
            self.update(qb, jt)
        return self.beta, {'method': self.name, 'poses': int(len(q_base)), **self.fit_info()}

    def fit_info(self):
        """Extra facts for fit()'s info dict."""
        return {}


class RowUpdates:
    """Linear updates with given rows, y = phi^T beta + e (the paper's rows, or MAP's): for
    experiments that precompute phi. Needs `_beta`, `n_updates`, `errors` and
    `_update(row, y, noise_var, err)`."""

    def update_row(self, phi_row, y=0.0, noise_var=None):
        """One row; returns the prediction error phi^T beta - y before the update."""
        phi_row = np.asarray(phi_row, dtype=float)
        err = float(phi_row @ self._beta - y)
        self._update(phi_row, float(y), noise_var, err)
        self.n_updates += 1
        self.errors.append(err)
        return err

    def update_rows(self, phi_rows, y=None, noise_var=None):
        """Sequential updates over rows (the online order)."""
        phi_rows = np.atleast_2d(phi_rows)
        y = np.zeros(len(phi_rows)) if y is None else np.broadcast_to(y, (len(phi_rows),))
        nv = (
            [None] * len(phi_rows)
            if noise_var is None
            else np.broadcast_to(noise_var, (len(phi_rows),))
        )
        return np.array([self.update_row(p, yy, v) for p, yy, v in zip(phi_rows, y, nv)])


@register_estimator('paper-gd')
class PaperGD(RowUpdates, Estimator):
    """beta <- beta - eta (phi^T beta - y) phi, the paper's eq. (update), eta = 300 (18c
    train_beta.cpp).

    mass_regularization u: the authors' optional penalty (u = 0 in all their runs), which adds
    u (sum m - M) to the error and u * [mass indicator] to the direction. `robot` may be None for
    row updates only.
    """

    def __init__(
        self,
        robot,
        beta0,
        eta=300.0,
        x_tol=2e-3,
        window=10,
        mass_regularization=0.0,
        total_mass=None,
    ):
        self.eta = float(eta)
        self.x_tol = float(x_tol)
        self.window = int(window)
        self.u = float(mass_regularization)
        self.mass_indicator = np.zeros(len(beta0))
        self.mass_indicator[0::4] = 1.0
        self.total_mass = float(
            np.sum(np.asarray(beta0)[0::4]) if total_mass is None else total_mass
        )
        super().__init__(robot, beta0)

    def update(self, q_base, joints, sigma=None):
        """phi at the measured pitch, y = 0 (the paper's step has no noise model: sigma unused)."""
        return self.update_row(phi_fn(self.robot, [q_base], np.atleast_2d(joints))[0], 0.0)

    def _step(self, phi_row, y, err):
        if self.u:
            err_u = err + self.u * (self.mass_indicator @ self._beta - self.total_mass)
            return -self.eta * err_u * (phi_row + self.u * self.mass_indicator)
        return -self.eta * err * phi_row

    def _update(self, phi_row, y, noise_var, err):
        self._beta += self._step(phi_row, y, err)

    @property
    def converged(self):
        """The paper's stop rule: |phi^T beta| < x_tol for the last `window` poses."""
        return (
            len(self.errors) >= self.window
            and max(abs(e) for e in self.errors[-self.window :]) < self.x_tol
        )

    def fit_info(self):
        return {'converged_paper_rule': bool(self.converged)}


@register_estimator('paper-gd-mass')
class PaperGDMass(PaperGD):
    """Paper GD with the total-mass constraint sum(m) = M_known, by a Lagrange multiplier: each
    step is followed by the projection min (beta'-b)^T W^-1 (beta'-b) s.t. a^T beta' = M, i.e.
    beta' = b + W a (M - a^T b) / (a^T W a). W weights which masses absorb the correction; by
    default proportional to the CAD masses (W = diag(m0) on mass entries), so the Base takes most
    of it. `weights='euclidean'` spreads it evenly (the plain Euclidean projection). M_known:
    total_mass, else the robot's nominal mass, else beta0's."""

    def __init__(
        self, robot, beta0, eta=300.0, x_tol=2e-3, window=10, total_mass=None, weights='mass'
    ):
        beta0 = np.asarray(beta0, dtype=float)
        a = np.zeros(len(beta0))
        a[0::4] = 1.0
        if isinstance(weights, str):
            if weights == 'mass':
                w = np.abs(beta0) * a
            elif weights == 'euclidean':
                w = a.copy()
            else:
                raise ValueError(
                    f'weights must be "mass", "euclidean" or an array, not {weights!r}'
                )
        else:
            w = np.asarray(weights, dtype=float) * a
        self._wa = w
        if total_mass is None and robot is not None:
            total_mass = robot.nominal_mass
        super().__init__(robot, beta0, eta=eta, x_tol=x_tol, window=window, total_mass=total_mass)

    def _project(self, b):
        a = self.mass_indicator
        return b + self._wa * (self.total_mass - a @ b) / (a @ self._wa)

    def reset(self, beta0=None):
        super().reset(beta0)
        self._beta = self._project(self._beta)

    def _update(self, phi_row, y, noise_var, err):
        self._beta = self._project(self._beta + self._step(phi_row, y, err))


class MAPEstimator(RowUpdates):
    """Bayesian linear regression, recursive form: the linear-Gaussian core of MAPOnline (rows in).

    Prior beta ~ N(beta0, diag(prior_std^2)), conditioned on the equality constraints A beta = b
    (exact: the posterior covariance has A Sigma = 0, so every later update keeps them). Each row
    adds y = phi^T beta + e, e ~ N(0, noise_var):
        k = Sigma phi / (phi^T Sigma phi + r),  beta += k (y - phi^T beta),  Sigma -= k phi^T
        Sigma.
    A negative noise_var removes information (the errors-in-variables correction of
    balanced_pose_rows); it must leave Sigma positive definite (phi^T Sigma phi + r < 0).
    """

    def __init__(self, beta0, prior_std, noise_var=1e-6, A=None, b=None):
        self.prior_std = np.asarray(prior_std, dtype=float)
        if np.any(self.prior_std <= 0):
            raise ValueError(
                'prior_std must be positive (fix entries with equality constraints instead)'
            )
        self.default_noise_var = float(noise_var)
        self.beta0 = np.array(beta0, dtype=float)
        n = len(self.beta0)
        self.A = np.zeros((0, n)) if A is None else np.atleast_2d(np.asarray(A, dtype=float))
        self.b = np.zeros(0) if b is None else np.atleast_1d(np.asarray(b, dtype=float))
        self.reset()

    def reset(self):
        self._beta = self.beta0.copy()
        self._sigma = np.diag(self.prior_std**2)
        if len(self.A):
            self._beta, self._sigma = condition_on_constraints(
                self._beta, self._sigma, self.A, self.b
            )
        self.prior_mean = self._beta.copy()
        self.n_updates = 0
        self.errors = []

    @property
    def beta(self):
        return self._beta.copy()

    @property
    def covariance(self):
        return self._sigma.copy()

    def _update(self, phi_row, y, noise_var, err):
        r = self.default_noise_var if noise_var is None else float(noise_var)
        u = self._sigma @ phi_row
        s = float(phi_row @ u) + r
        k = u / s
        self._beta -= k * err
        self._sigma -= np.outer(k, u)
        self._sigma = 0.5 * (self._sigma + self._sigma.T)

    def constraint_residual(self):
        return self.A @ self._beta - self.b if len(self.A) else np.zeros(0)


@register_estimator('map-online')
class MAPOnline(Estimator):
    """MAP on the CoM-angle model, online: one rank-one update per pose (rows linearised at the
    current linearisation point beta_lin), and a re-linearisation (a Gauss-Newton pass over every
    pose so far, from the prior) whenever the linear model is off by more than `relinearize_tol`
    radians of CoM angle at any stored pose. relinearize_tol=None never re-linearises (then it
    equals map_batch on the rows at the prior mean). finalize() iterates to the batch MAP (=
    map_gauss_newton).

    Defaults from the robot: prior_std = physical_prior_std(robot, beta0, mass_frac, com_std);
    (A, b) = equality_constraints(robot, total_mass or the nominal mass): the known total mass and
    the wheel CoMs on the axle (pass A of shape (0, n) for none)."""

    def __init__(
        self,
        robot,
        beta0,
        prior_std=None,
        noise=None,
        A=None,
        b=None,
        relinearize_tol=1e-4,
        mass_frac=0.1,
        com_std=0.03,
        total_mass=None,
    ):
        self.noise = noise or NoiseModel()
        if prior_std is None:
            prior_std = physical_prior_std(robot, beta0, mass_frac=mass_frac, com_std=com_std)
        self.prior_std = np.asarray(prior_std, dtype=float)
        if A is None:
            total_mass = robot.nominal_mass if total_mass is None else total_mass
            A, b = equality_constraints(robot, total_mass)
        self.A, self.b = A, b
        self.relinearize_tol = relinearize_tol
        super().__init__(robot, beta0)

    def reset(self, beta0=None):
        super().reset(beta0)
        self._map = MAPEstimator(self.beta0, self.prior_std, A=self.A, b=self.b)
        self.prior_mean = self._map.prior_mean
        self._beta = self._map.beta
        self.beta_lin = self.prior_mean.copy()
        self.q, self.joints, self.sigmas = [], [], []
        self.relinearizations = 0

    @property
    def covariance(self):
        return self._map.covariance

    def update(self, q_base, joints, sigma=None):
        """sigma: this pose's own pitch standard error (rad), added in quadrature to the noise
        model's (NoiseModel.pitch_std; None: the model's alone)."""
        joints = np.asarray(joints, dtype=float).reshape(-1)
        x_err = float(phi_fn(self.robot, [q_base], joints[None])[0] @ self._beta)
        self.q.append(float(q_base))
        self.joints.append(joints.copy())
        self.sigmas.append(math.nan if sigma is None else float(sigma))
        rows, y, var = balanced_pose_rows(
            self.robot,
            [q_base],
            joints[None],
            self.beta_lin,
            self.noise,
            sigma_pitch=self.sigmas[-1:],
        )
        self._map.update_row(rows[0], float(y[0]), float(var[0]))
        self._beta = self._map.beta
        if self.relinearize_tol is not None and self._linearisation_error() > self.relinearize_tol:
            self._relinearize(iterations=1)
        self.n_updates += 1
        self.errors.append(x_err)
        return x_err

    def _linearisation_error(self):
        """max over stored poses of |h(beta) - h_lin(beta)| (rad of CoM angle) at the current
        estimate."""
        q, j = np.array(self.q), np.array(self.joints)
        P, Psi = phi_fn(self.robot, q, j), pitch_rows(self.robot, q, j)
        x_l, z_l = P @ self.beta_lin, Psi @ self.beta_lin
        h_lin = x_l / z_l + ((P - (x_l / z_l)[:, None] * Psi) @ (self._beta - self.beta_lin)) / z_l
        h = (P @ self._beta) / (Psi @ self._beta)
        return float(np.abs(h - h_lin).max())

    def _relinearize(self, iterations=1):
        beta, cov, lin = map_gauss_newton(
            self.robot,
            np.array(self.q),
            np.array(self.joints),
            self.beta0,
            self.prior_std,
            self.noise,
            self.A,
            self.b,
            iterations=iterations,
            beta_start=self._beta,
            sigma_pitch=np.array(self.sigmas),
        )
        self._set_posterior(beta, cov, lin)
        self.relinearizations += 1

    def _set_posterior(self, beta, cov, lin):
        self.beta_lin = lin
        self._map._beta, self._map._sigma = beta.copy(), cov.copy()
        self._beta = beta.copy()

    def constraint_residual(self):
        return self._map.constraint_residual()

    def finalize(self, iterations=20):
        """Iterate the Gauss-Newton passes to convergence: the batch MAP of all poses so far."""
        if self.q:
            self._relinearize(iterations)
        return self.beta

    def fit_info(self):
        return {
            'covariance_trace': float(np.trace(self.covariance)),
            'relinearizations': self.relinearizations,
        }


@register_estimator('map')
class MAP(MAPOnline):
    """map: the posterior of map-online, with fit() in closed form: the batch Gauss-Newton MAP of
    all poses (map_gauss_newton), then, with physical=True, the inequality-constrained QP if the
    Gaussian MAP leaves the physically consistent region (map_constrained). Online: map-online.

    calibrate=True: the noise and prior scales (sigma_pitch, mass_frac, com_std) come from the
    training poses by evidence maximisation (calibrate_scales) before the fit. pitch_offset_std
    (rad): also estimate an IMU pitch offset with that prior std (offset_rows); the estimate and
    its posterior std are `pitch_offset` and `pitch_offset_std_post` (in fit's info too)."""

    def __init__(
        self,
        robot,
        beta0,
        prior_std=None,
        noise=None,
        A=None,
        b=None,
        relinearize_tol=1e-4,
        mass_frac=0.1,
        com_std=0.03,
        total_mass=None,
        physical=True,
        calibrate=False,
        pitch_offset_std=None,
    ):
        self.physical = physical
        self.calibrate = calibrate
        self.pitch_offset_std = pitch_offset_std
        self.calibration = None
        self.pitch_offset = self.pitch_offset_std_post = None
        super().__init__(
            robot, beta0, prior_std, noise, A, b, relinearize_tol, mass_frac, com_std, total_mass
        )

    def fit(self, q_base, joints):
        q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
        joints = np.atleast_2d(joints)
        info = {'method': self.name, 'poses': int(len(q_base))}
        if self.calibrate:
            self.calibration = calibrate_scales(
                self.robot,
                q_base,
                joints,
                self.beta0,
                self.A,
                self.b,
                pitch_offset_std=self.pitch_offset_std,
            )
            c = self.calibration
            self.noise = NoiseModel(sigma_imu_rad=c['sigma_pitch_rad'])
            self.prior_std = physical_prior_std(
                self.robot, self.beta0, mass_frac=c['mass_frac'], com_std=c['com_std_m']
            )
            info['calibration'] = dict(c)
        self.reset()
        n = self.robot.n_beta
        beta, cov, lin = map_gauss_newton(
            self.robot,
            q_base,
            joints,
            self.beta0,
            self.prior_std,
            self.noise,
            self.A,
            self.b,
            pitch_offset_std=self.pitch_offset_std,
        )
        if self.pitch_offset_std is not None:
            self.pitch_offset = float(beta[n])
            self.pitch_offset_std_post = float(math.sqrt(cov[n, n]))
            info.update(
                pitch_offset_rad=self.pitch_offset, pitch_offset_std_rad=self.pitch_offset_std_post
            )
            q_base = q_base - self.pitch_offset  # the poses as the model now sees them
            beta, cov, lin = beta[:n], cov[:n, :n], lin[:n]
        info['covariance_trace'] = float(np.trace(cov))
        if self.physical:
            G, h = inequality_constraints(self.robot)
            info['inequality_qp'] = bool(np.any(G @ beta < h - 1e-12))
            if info['inequality_qp']:
                rows, y, var = balanced_pose_rows(self.robot, q_base, joints, lin, self.noise)
                beta = map_constrained(
                    self.beta0, self.prior_std, rows, y, var, self.A, self.b, G, h, beta_start=beta
                )
        self.q = [float(v) for v in q_base]
        self.joints = [j.copy() for j in np.asarray(joints, dtype=float)]
        self.sigmas = [math.nan] * len(self.q)
        self.n_updates = len(q_base)
        self._set_posterior(beta, cov, lin)
        return self.beta, info


def cross_validate(method, robot, q_base, joints, beta0, folds=10, seed=0, **kw):
    """k-fold CV of the estimator's `fit` (options `kw`) on balanced poses: predictions
    x_com = phi^T beta on each held-out record and the pitch error atan2(x_com, psi^T beta), at
    the measured pitch less the estimator's `pitch_offset` if it estimated one. Training records
    keep their order."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    joints = np.atleast_2d(joints)
    n = len(q_base)
    folds = max(2, min(int(folds), n))
    parts = np.array_split(np.random.default_rng(seed).permutation(n), folds)
    P = phi_fn(robot, q_base, joints)
    Psi = pitch_rows(robot, q_base, joints)
    pred = np.empty(n)
    pitch = np.empty(n)
    for f in parts:
        tr = np.setdiff1d(np.arange(n), f)
        estimator = make_estimator(method, robot, beta0, **kw)
        beta, _ = estimator.fit(q_base[tr], joints[tr])
        offset = getattr(estimator, 'pitch_offset', None)
        Pf, Psif = P[f], Psi[f]
        if offset:
            Pf, Psif = (
                phi_fn(robot, q_base[f] - offset, joints[f]),
                pitch_rows(robot, q_base[f] - offset, joints[f]),
            )
        pred[f] = Pf @ beta
        pitch[f] = np.arctan2(pred[f], Psif @ beta)
    return pred, pitch
