"""Estimators of the mass model beta from balanced poses (pure numpy; no rclpy).

Measurement model. At a balanced pose the whole-robot CoM is over the axle, so the paper's
x_com = phi(q)^T beta (phi divided by the nominal mass, krang_model.com.phi) is 0. What we observe
is q_base from the IMU, off by a pitch error dq (IMU noise, hand-balancing repeatability). Since
    phi(q)^T beta = (sin q Y - cos q Z) / M_nom   (Y, Z: base-frame mass moment, krang_model.com)
    psi(q)^T beta := d(phi^T beta)/dq_base = (cos q Y + sin q Z) / M_nom = M(beta)/M_nom * z_com(q),
a pitch error dq shows up as phi(q_meas)^T beta = z_com dq (+ O(dq^2)), z_com the CoM height above
the axle (frame 0): the x_com noise is sigma_pitch * z_com.

Balanced poses give only phi^T beta = 0, a homogeneous system: beta and c*beta fit equally well, and
the Base and wheel masses (phi = 0) can absorb any change of total mass, so even the known total
mass does not fix the scale of the mass moments (notes §0.2; identifiability.py). The scale comes
from the prior. Worse, with a noisy pitch the regressor itself is noisy (errors in variables): the
paper's residual phi(q_meas)^T beta = z_beta dq is smaller for a smaller beta, so least squares on it
shrinks the whole moment vector, and nothing in the data resists (-8 cm of CoM height after 400
noisy poses, docs/learning.md). The MAP estimator therefore uses the scale-free CoM angle at the
measured pitch, h(beta) = phi^T beta / psi^T beta = tan(CoM angle from vertical), with h(beta_true) =
tan(-dq): linearised at beta_lin it is the linear row g = phi - h_lin psi (g^T beta_lin = 0: no pull
along the scale), and Gauss-Newton re-linearises (balanced_pose_rows, map_gauss_newton).

Estimators (common interface: `update_pose(robot, q_meas, joints, noise)` learns from one balanced
pose with the estimator's own measurement model (use this one); `update(row, y=0.0, noise_var=None)`
a linear update with a given row; both return the paper's x_com error before the update; `beta`,
`covariance`, `n_updates`, `reset()`; `make_estimator(name, ...)`):
- `paper-gd`: the paper's GD, beta <- beta - eta (phi^T beta - y) phi (eta = 300), with the stop rule
  |phi^T beta| < x_tol for the last `window` poses, and the authors' unused mass penalty u.
- `paper-gd-mass`: the same step followed by the Lagrange-multiplier projection that keeps the total
  mass at M_known (the constraint the paper describes and the authors left off).
- `map` / `map-online`: Bayesian MAP with a Gaussian prior N(beta0, diag(s^2)) from physical
  plausibility and hard linear equality constraints (known total mass, wheel CoMs on the axle)
  imposed by conditioning the prior on them. `MAPEstimator` is the linear-Gaussian core: a Kalman /
  recursive least-squares rank-one update of (mean, covariance); `map_batch` solves the same problem
  in one go (null-space form) with the same result. `MAPOnline` feeds it the CoM-angle rows and
  re-linearises (a batch Gauss-Newton pass over the poses so far) when the estimate has moved enough
  to matter; `map_gauss_newton` is the batch form; `MAPOnline.finalize()` equals it.
`map_constrained` adds the inequality constraints of physical consistency (positive masses, every
CoM inside the inflated collision box of its link) as a QP, used when the Gaussian MAP violates them.
"""
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from krang_model.com import base_regressor, phi as phi_fn

ESTIMATORS = ('paper-gd', 'paper-gd-mass', 'map', 'map-online')


# ---------------------------------------------------------------- measurement model
def pitch_sensitivity(robot, q_base, joints, beta):
    """d(phi^T beta)/d q_base (N,) = M(beta)/M_nom * z_com: how a pitch error shows up in x_com (m/rad)."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    base = base_regressor(robot, joints) @ np.asarray(beta, dtype=float)     # (N, 3) base-frame moment
    return (np.cos(q_base) * base[:, 1] + np.sin(q_base) * base[:, 2]) / robot.nominal_mass


def pitch_rows(robot, q_base, joints):
    """psi(q) (N, n_beta) = d phi(q) / d q_base, so that psi^T beta = pitch_sensitivity."""
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    base = base_regressor(robot, joints)
    return (np.cos(q_base)[:, None] * base[:, 1] + np.sin(q_base)[:, None] * base[:, 2]) / robot.nominal_mass


def balanced_pose_rows(robot, q_meas, joints, beta_lin, noise=None, model='angle'):
    """Linear measurement rows of balanced poses for MAPEstimator / map_batch: (rows, y, var).

    model='angle' (default, one row per pose): the CoM angle at the measured pitch,
    h(beta) = phi^T beta / psi^T beta, linearised at beta_lin (x = phi^T beta_lin, z = psi^T beta_lin,
    h = x / z) and multiplied by z:   g^T beta = -x + z dq,   g = phi - h psi,
    var = (sigma_pitch z)^2 + sigma_x^2. g^T beta_lin = 0, so the rows carry no information along the
    scale of beta_lin, whatever the noise; the innovation g^T beta_lin - y = x is the paper's x_com error.
    model='phi': the paper's regression, row phi, y = 0, same variance (biased by the noisy pitch).
    model='eiv': 'phi' plus the first-order errors-in-variables correction, a second row psi with
    y = 0 and NEGATIVE variance -r/sigma^2 (removes the expected sigma^2 psi psi^T / r; corrected least
    squares); unbiased to first order only (second-order bias grows with the number of poses)."""
    noise = noise or NoiseModel()
    q_meas = np.atleast_1d(np.asarray(q_meas, dtype=float))
    joints = np.atleast_2d(joints)
    P = phi_fn(robot, q_meas, joints)
    Psi = pitch_rows(robot, q_meas, joints)
    beta_lin = np.asarray(beta_lin, dtype=float)
    x = P @ beta_lin
    z = Psi @ beta_lin
    r = (noise.sigma_pitch * z) ** 2 + noise.sigma_x_m ** 2
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
    var[0::2], var[1::2] = r, -r / noise.sigma_pitch ** 2
    return rows, np.zeros(2 * n), var


@dataclass(frozen=True)
class NoiseModel:
    """Noise of one balanced-pose measurement y = phi(q_meas)^T beta = 0.

    sigma_imu_rad: IMU pitch noise (0.1 deg by default); sigma_hand_rad: repeatability of finding the
    balance by hand (hardware: the cancelled attempts of the real-data kit scatter by ~9 mrad median);
    sigma_x_m: a floor for everything else (model error), in metres of x_com.
    """

    sigma_imu_rad: float = math.radians(0.1)
    sigma_hand_rad: float = 0.0
    sigma_x_m: float = 0.0

    @property
    def sigma_pitch(self):
        return math.hypot(self.sigma_imu_rad, self.sigma_hand_rad)

    def variance(self, robot, q_base, joints, beta_ref):
        """(N,) variance of y for each pose (z_com from the reference beta, e.g. the prior mean)."""
        dz = pitch_sensitivity(robot, q_base, joints, beta_ref)
        return (self.sigma_pitch * dz) ** 2 + self.sigma_x_m ** 2


# ---------------------------------------------------------------- priors and physical constraints
def physical_prior_std(robot, beta0=None, mass_frac=0.1, com_std=0.03, mass_floor=1e-3):
    """Prior std per beta entry from physical plausibility: each mass known to `mass_frac` (relative,
    at least `mass_floor` kg), each CoM coordinate to `com_std` metres. For the moment m*c with m and c
    independent: var(m c) = (m s_c)^2 + (c s_m)^2 + (s_m s_c)^2."""
    beta0 = robot.nominal_beta if beta0 is None else np.asarray(beta0, dtype=float)
    std = np.empty_like(beta0)
    for i in range(robot.n_bodies):
        m = beta0[4 * i]
        c = beta0[4 * i + 1:4 * i + 4] / m if m != 0 else np.zeros(3)
        s_m = max(mass_frac * abs(m), mass_floor)
        std[4 * i] = s_m
        std[4 * i + 1:4 * i + 4] = np.sqrt((m * com_std) ** 2 + (c * s_m) ** 2 + (s_m * com_std) ** 2)
    return std


def recipe_prior_std(beta0, max_deviation=0.5, max_offset=0.5, mass_std=1e-6):
    """Prior std matching the authors' erroneous-beta recipe (masses exact; v + U(-d,d) v + U(-o,o)):
    var = (d^2 v^2 + o^2) / 3 per moment entry, with v taken as the start value."""
    beta0 = np.asarray(beta0, dtype=float)
    std = np.sqrt((max_deviation ** 2 * beta0 ** 2 + max_offset ** 2) / 3.0)
    std[0::4] = mass_std
    return std


def equality_constraints(robot, total_mass=None, wheels_on_axle=True):
    """(A, b) of the hard linear constraints A beta = b: sum of masses = total_mass (if given) and
    each wheel's m*y = m*z = 0 (its CoM on its own axis, which is the axle; the wheel frame's x axis
    is the axle)."""
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
    """Plausible CoM region of every body, in its own frame: the axis-aligned bounding box of its URDF
    collision shape grown by `inflate` metres on every side, and always containing the CAD CoM
    (grown likewise). Bodies without collision geometry (the gripper plates) get the box of
    `inflate` around the CAD CoM. Returns (lo, hi) arrays (n_bodies, 3)."""
    root = ET.parse(robot.urdf_path).getroot()
    lo = np.empty((robot.n_bodies, 3))
    hi = np.empty((robot.n_bodies, 3))
    beta0 = robot.nominal_beta
    for i, name in enumerate(robot.body_names):
        cad = beta0[4 * i + 1:4 * i + 4] / beta0[4 * i]
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
    xyz = np.zeros(3) if origin is None else np.array([float(v) for v in origin.get('xyz', '0 0 0').split()])
    rpy = np.zeros(3) if origin is None else np.array([float(v) for v in origin.get('rpy', '0 0 0').split()])
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
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    return xyz + (signs * half) @ _rpy(rpy).T


def _rpy(rpy):
    r, p, y = rpy
    cx, sx, cy, sy, cz, sz = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
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
        com = beta[4 * i + 1:4 * i + 4] / m if m != 0 else np.full(3, np.nan)
        com_cad = cad[4 * i + 1:4 * i + 4] / cad[4 * i]
        moved = float(np.linalg.norm(com - com_cad))
        bodies.append({'name': name, 'mass': float(m), 'com': com.tolist(), 'com_moved_m': moved,
                       'mass_change_kg': float(m - cad[4 * i])})
        if not m > 0:
            violations.append(f'{name}: mass {m:.4g} kg is not positive')
            continue
        out = (com < lo[i] - tol) | (com > hi[i] + tol)
        if out.any():
            violations.append(f'{name}: CoM {np.round(com, 4).tolist()} m outside its plausible box '
                              f'[{np.round(lo[i], 3).tolist()}, {np.round(hi[i], 3).tolist()}]')
    for w in robot.wheel_body_ids:
        off = np.abs(beta[4 * w + 2:4 * w + 4])
        if off.max() > tol:
            violations.append(f'{robot.body_names[w]}: CoM off the axle (m*y, m*z = '
                              f'{beta[4 * w + 2]:.3g}, {beta[4 * w + 3]:.3g} kg m)')
    mass = float(beta[0::4].sum())
    if abs(mass - total_mass) > 1e-6 * total_mass:
        violations.append(f'total mass {mass:.3f} kg instead of {total_mass:.3f} kg')
    return {'ok': not violations, 'violations': violations, 'total_mass': mass, 'bodies': bodies}


# ---------------------------------------------------------------- estimators
class Estimator:
    """Common interface. Subclasses implement `_update(phi_row, y, noise_var)`."""

    name = 'estimator'

    def __init__(self, beta0):
        self.beta0 = np.array(beta0, dtype=float)
        self.reset()

    def reset(self):
        self._beta = self.beta0.copy()
        self.n_updates = 0
        self.errors = []          # prediction error phi^T beta - y before each update

    @property
    def beta(self):
        return self._beta.copy()

    @property
    def covariance(self):
        return None

    def predict(self, phi_rows):
        return np.atleast_2d(phi_rows) @ self._beta

    def update(self, phi_row, y=0.0, noise_var=None):
        """Learn from one balanced pose; returns the prediction error phi^T beta - y before the update."""
        phi_row = np.asarray(phi_row, dtype=float)
        err = float(phi_row @ self._beta - y)
        self._update(phi_row, float(y), noise_var, err)
        self.n_updates += 1
        self.errors.append(err)
        return err

    def update_pose(self, robot, q_meas, joints, noise=None):
        """Learn from one balanced pose given as (measured base pitch, joints in pose order): the paper
        estimators use phi(q) with y = 0; MAP overrides this with its errors-in-variables rows."""
        return self.update(phi_fn(robot, [q_meas], np.atleast_2d(joints))[0], 0.0)

    def update_many(self, phi_rows, y=None, noise_var=None):
        """Sequential updates over rows (the online order)."""
        phi_rows = np.atleast_2d(phi_rows)
        y = np.zeros(len(phi_rows)) if y is None else np.broadcast_to(y, (len(phi_rows),))
        nv = [None] * len(phi_rows) if noise_var is None else np.broadcast_to(noise_var, (len(phi_rows),))
        return np.array([self.update(p, yy, v) for p, yy, v in zip(phi_rows, y, nv)])


class PaperGD(Estimator):
    """beta <- beta - eta (phi^T beta - y) phi, the paper's eq. (update), eta = 300 (18c train_beta.cpp).

    mass_regularization u: the authors' optional penalty (u = 0 in all their runs), which adds
    u (sum m - M) to the error and u * [mass indicator] to the direction.
    """

    name = 'paper-gd'

    def __init__(self, beta0, eta=300.0, x_tol=2e-3, window=10, mass_regularization=0.0, total_mass=None):
        self.eta = float(eta)
        self.x_tol = float(x_tol)
        self.window = int(window)
        self.u = float(mass_regularization)
        self.mass_indicator = np.zeros(len(beta0))
        self.mass_indicator[0::4] = 1.0
        self.total_mass = float(np.sum(np.asarray(beta0)[0::4]) if total_mass is None else total_mass)
        super().__init__(beta0)

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
        return len(self.errors) >= self.window and max(abs(e) for e in self.errors[-self.window:]) < self.x_tol


class PaperGDMass(PaperGD):
    """Paper GD with the total-mass constraint sum(m) = M_known, by a Lagrange multiplier: each step is
    followed by the projection min (beta'-b)^T W^-1 (beta'-b) s.t. a^T beta' = M, i.e.
    beta' = b + W a (M - a^T b) / (a^T W a). W weights which masses absorb the correction; by default
    proportional to the CAD masses (W = diag(m0) on mass entries), so the Base takes most of it.
    `weights='euclidean'` spreads it evenly (the plain Euclidean projection)."""

    name = 'paper-gd-mass'

    def __init__(self, beta0, eta=300.0, x_tol=2e-3, window=10, total_mass=None, weights='mass'):
        beta0 = np.asarray(beta0, dtype=float)
        a = np.zeros(len(beta0))
        a[0::4] = 1.0
        if isinstance(weights, str):
            if weights == 'mass':
                w = np.abs(beta0) * a
            elif weights == 'euclidean':
                w = a.copy()
            else:
                raise ValueError(f'weights must be "mass", "euclidean" or an array, not {weights!r}')
        else:
            w = np.asarray(weights, dtype=float) * a
        self._wa = w
        super().__init__(beta0, eta=eta, x_tol=x_tol, window=window, total_mass=total_mass)

    def _project(self, b):
        a = self.mass_indicator
        return b + self._wa * (self.total_mass - a @ b) / (a @ self._wa)

    def reset(self):
        super().reset()
        self._beta = self._project(self._beta)

    def _update(self, phi_row, y, noise_var, err):
        self._beta = self._project(self._beta + self._step(phi_row, y, err))


class MAPEstimator(Estimator):
    """Bayesian linear regression, recursive form.

    Prior beta ~ N(beta0, diag(prior_std^2)), conditioned on the equality constraints A beta = b
    (exact: the posterior covariance has A Sigma = 0, so every later update keeps them). Each row
    adds y = phi^T beta + e, e ~ N(0, noise_var):
        k = Sigma phi / (phi^T Sigma phi + r),  beta += k (y - phi^T beta),  Sigma -= k phi^T Sigma.
    A negative noise_var removes information (the errors-in-variables correction of
    balanced_pose_rows); it must leave Sigma positive definite (phi^T Sigma phi + r < 0).
    """

    name = 'map'

    def __init__(self, beta0, prior_std, noise_var=1e-6, A=None, b=None):
        self.prior_std = np.asarray(prior_std, dtype=float)
        if np.any(self.prior_std <= 0):
            raise ValueError('prior_std must be positive (fix entries with equality constraints instead)')
        self.default_noise_var = float(noise_var)
        n = len(beta0)
        self.A = np.zeros((0, n)) if A is None else np.atleast_2d(np.asarray(A, dtype=float))
        self.b = np.zeros(0) if b is None else np.atleast_1d(np.asarray(b, dtype=float))
        super().__init__(beta0)

    def reset(self):
        super().reset()
        self._sigma = np.diag(self.prior_std ** 2)
        if len(self.A):
            self._beta, self._sigma = condition_on_constraints(self._beta, self._sigma, self.A, self.b)
        self.prior_mean = self._beta.copy()

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

    def update_pose(self, robot, q_meas, joints, noise=None, beta_lin=None, model='angle'):
        """Linear update from one balanced pose with the rows of balanced_pose_rows linearised at
        beta_lin (default: the prior mean; fixed, so the result equals map_batch on the same rows).
        For re-linearisation use MAPOnline."""
        rows, y, var = balanced_pose_rows(robot, [q_meas], np.atleast_2d(joints),
                                          self.prior_mean if beta_lin is None else beta_lin, noise, model)
        x_err = float(phi_fn(robot, [q_meas], np.atleast_2d(joints))[0] @ self._beta)
        for k in range(len(rows)):
            self._update(rows[k], float(y[k]), float(var[k]), float(rows[k] @ self._beta - y[k]))
        self.n_updates += 1
        self.errors.append(x_err)
        return x_err

    def constraint_residual(self):
        return self.A @ self._beta - self.b if len(self.A) else np.zeros(0)


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
        minimise (beta-beta0)^T P0^-1 (beta-beta0) + sum_i (y_i - phi_i^T beta)^2 / r_i  s.t. A beta = b.
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
        raise np.linalg.LinAlgError('map_batch: the posterior information is not positive definite (negative-'
                                    'variance rows removed more information than the prior and data hold)') from None
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
    from scipy.linalg import cho_solve
    return cho_solve((L, True), g)


_BASIS_CACHE = {}


def _constraint_basis(A, b, n):
    """(beta_p, Z): a particular solution of A beta = b and an orthonormal basis of the null space of A."""
    key = (A.tobytes(), b.tobytes(), n)
    hit = _BASIS_CACHE.get(key)
    if hit is None:
        beta_p = np.linalg.lstsq(A, b, rcond=None)[0] if len(A) else np.zeros(n)
        hit = (beta_p, null_space(A, n))
        if len(_BASIS_CACHE) > 64:
            _BASIS_CACHE.clear()
        _BASIS_CACHE[key] = hit
    return hit


def angle_rows(P, Psi, beta_lin, noise=None):
    """The 'angle' rows of balanced_pose_rows from precomputed phi (P) and psi (Psi) rows."""
    noise = noise or NoiseModel()
    x = P @ beta_lin
    z = Psi @ beta_lin
    return P - (x / z)[:, None] * Psi, -x, (noise.sigma_pitch * z) ** 2 + noise.sigma_x_m ** 2


def map_gauss_newton(robot, q_meas, joints, beta0, prior_std, noise=None, A=None, b=None, iterations=20,
                     tol=1e-10, beta_start=None):
    """Batch MAP of the CoM-angle model by Gauss-Newton: linearise every pose at the current iterate
    (start: beta_start or the prior mean), solve the linear MAP, repeat until the step is below tol
    (relative to |beta0|). Returns (beta, covariance, beta_lin), beta_lin being the linearisation
    point of the last solve (= beta at convergence)."""
    q_meas = np.atleast_1d(np.asarray(q_meas, dtype=float))
    joints = np.atleast_2d(joints)
    return map_gauss_newton_rows(phi_fn(robot, q_meas, joints), pitch_rows(robot, q_meas, joints), beta0,
                                 prior_std, noise, A, b, iterations, tol, beta_start)


def map_gauss_newton_rows(P, Psi, beta0, prior_std, noise=None, A=None, b=None, iterations=20, tol=1e-10,
                          beta_start=None, covariance=True):
    """map_gauss_newton from precomputed phi and psi rows of the poses (measured pitch)."""
    beta0 = np.asarray(beta0, dtype=float)
    lin = beta0.copy() if beta_start is None else np.asarray(beta_start, dtype=float).copy()
    scale = np.abs(beta0).max()
    for it in range(max(1, iterations)):
        rows, y, var = angle_rows(P, Psi, lin, noise)
        beta, _ = map_batch(beta0, prior_std, rows, y, var, A, b, covariance=False)
        if np.abs(beta - lin).max() < tol * scale or it == iterations - 1:
            break
        lin = beta
    beta, cov = map_batch(beta0, prior_std, rows, y, var, A, b, covariance=covariance)
    return beta, cov, lin


class MAPOnline(Estimator):
    """MAP on the CoM-angle model, online: one rank-one update per pose (rows linearised at the current
    linearisation point beta_lin), and a re-linearisation (a Gauss-Newton pass over every pose so far,
    from the prior) whenever the linear model is off by more than `relinearize_tol` radians of CoM
    angle at any stored pose. relinearize_tol=None never re-linearises (then it equals map_batch on
    the rows at the prior mean). finalize() iterates to the batch MAP (= map_gauss_newton)."""

    name = 'map-online'

    def __init__(self, robot, beta0, prior_std, noise=None, A=None, b=None, relinearize_tol=1e-4):
        self.robot = robot
        self.noise = noise or NoiseModel()
        self.prior_std = np.asarray(prior_std, dtype=float)
        self.A, self.b = A, b
        self.relinearize_tol = relinearize_tol
        super().__init__(beta0)

    def reset(self):
        super().reset()
        self._map = MAPEstimator(self.beta0, self.prior_std, A=self.A, b=self.b)
        self.prior_mean = self._map.prior_mean
        self._beta = self._map.beta
        self.beta_lin = self.prior_mean.copy()
        self.q, self.joints = [], []
        self.relinearizations = 0

    @property
    def covariance(self):
        return self._map.covariance

    def _update(self, row, y, noise_var, err):          # plain linear update (given rows)
        self._map.update(row, y, self._map.default_noise_var if noise_var is None else noise_var)
        self._beta = self._map.beta

    def update_pose(self, robot, q_meas, joints, noise=None):
        noise = noise or self.noise
        self.noise = noise
        joints = np.asarray(joints, dtype=float).reshape(-1)
        x_err = float(phi_fn(robot, [q_meas], joints[None])[0] @ self._beta)
        self.q.append(float(q_meas))
        self.joints.append(joints.copy())
        rows, y, var = balanced_pose_rows(robot, [q_meas], joints[None], self.beta_lin, noise)
        self._map.update(rows[0], float(y[0]), float(var[0]))
        self._beta = self._map.beta
        if self.relinearize_tol is not None and self._linearisation_error() > self.relinearize_tol:
            self._relinearize(iterations=1)
        self.n_updates += 1
        self.errors.append(x_err)
        return x_err

    def _linearisation_error(self):
        """max over stored poses of |h(beta) - h_lin(beta)| (rad of CoM angle) at the current estimate."""
        q, j = np.array(self.q), np.array(self.joints)
        P, Psi = phi_fn(self.robot, q, j), pitch_rows(self.robot, q, j)
        x_l, z_l = P @ self.beta_lin, Psi @ self.beta_lin
        h_lin = x_l / z_l + ((P - (x_l / z_l)[:, None] * Psi) @ (self._beta - self.beta_lin)) / z_l
        h = (P @ self._beta) / (Psi @ self._beta)
        return float(np.abs(h - h_lin).max())

    def _relinearize(self, iterations=1):
        beta, cov, lin = map_gauss_newton(self.robot, np.array(self.q), np.array(self.joints), self.beta0,
                                          self.prior_std, self.noise, self.A, self.b, iterations=iterations,
                                          beta_start=self._beta)
        self.beta_lin = lin
        self._map._beta, self._map._sigma = beta.copy(), cov.copy()
        self._beta = beta.copy()
        self.relinearizations += 1

    def constraint_residual(self):
        return self._map.A @ self._beta - self._map.b if len(self._map.A) else np.zeros(0)

    def finalize(self, iterations=20):
        """Iterate the Gauss-Newton passes to convergence: the batch MAP of all poses so far."""
        if self.q:
            self._relinearize(iterations)
        return self.beta


def map_constrained(beta0, prior_std, phi_rows, y=None, noise_var=1e-6, A=None, b=None, G=None, h=None,
                    beta_start=None):
    """MAP with the equality constraints A beta = b AND the inequalities G beta >= h (a convex QP;
    solved on the null space of A by scipy's SLSQP with exact gradients). Returns beta."""
    from scipy.optimize import minimize

    beta0 = np.asarray(beta0, dtype=float)
    n = len(beta0)
    Phi = np.atleast_2d(np.asarray(phi_rows, dtype=float)).reshape(-1, n)
    y = np.zeros(len(Phi)) if y is None else np.asarray(y, dtype=float)
    r = np.broadcast_to(np.asarray(noise_var, dtype=float), (len(Phi),))
    A = np.zeros((0, n)) if A is None else np.atleast_2d(A)
    b = np.zeros(0) if b is None else np.atleast_1d(b)
    start, _ = map_batch(beta0, prior_std, Phi, y, r, A, b) if beta_start is None else (beta_start, None)
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
    res = minimize(lambda z: 0.5 * z @ Hs @ z - gs @ z, np.zeros(Z.shape[1]), jac=lambda z: Hs @ z - gs,
                   constraints=[{'type': 'ineq', 'fun': lambda z: GZ @ z - hz, 'jac': lambda z: GZ}],
                   method='SLSQP', options={'maxiter': 500, 'ftol': 1e-14})
    beta = start + Z @ res.x
    return beta


def make_estimator(name, beta0, robot=None, **kw):
    """An estimator by name (for the ROS node and the CLI): paper-gd, paper-gd-mass, map, map-online.

    map / map-online with a robot: MAPOnline (CoM-angle model, re-linearising) with the physical prior
    of `robot` (options mass_frac, com_std, or prior_std), the known total mass (total_mass, default
    robot.nominal_mass) and the wheel constraints, noise (a NoiseModel) and relinearize_tol. Without a
    robot: the linear MAPEstimator (needs prior_std; feed it rows with update())."""
    if name == 'paper-gd':
        kw.pop('total_mass', None)
        return PaperGD(beta0, **kw)
    if name == 'paper-gd-mass':
        if kw.get('total_mass') is None:
            kw['total_mass'] = None if robot is None else robot.nominal_mass
        return PaperGDMass(beta0, **kw)
    if name in ('map', 'map-online'):
        if robot is None:
            if 'prior_std' not in kw:
                raise ValueError('map without a robot needs prior_std')
            est = MAPEstimator(beta0, **kw)
            est.name = name
            return est
        prior_kw = {k: kw.pop(k) for k in ('mass_frac', 'com_std') if k in kw}
        total_mass = kw.pop('total_mass', None)
        total_mass = robot.nominal_mass if total_mass is None else total_mass
        prior_std = kw.pop('prior_std', None)
        if prior_std is None:
            prior_std = physical_prior_std(robot, beta0, **prior_kw)
        if 'A' not in kw:
            kw['A'], kw['b'] = equality_constraints(robot, total_mass)
        est = MAPOnline(robot, beta0, prior_std, **kw)
        est.name = name
        return est
    raise ValueError(f'unknown estimator {name!r}; choose one of {ESTIMATORS}')


def fit(method, robot, q_base, joints, beta0, noise=None, mass_frac=0.1, com_std=0.03, total_mass=None,
        eta=300.0, physical=True):
    """Learn beta from balanced poses (measured q_base, joints) with one method; returns (beta, info).

    paper-gd / paper-gd-mass / map-online: one pass in the given (online) order. map: the batch MAP
    (same posterior as map-online), then, with physical=True, the inequality-constrained QP if the
    Gaussian MAP leaves the physically consistent region (map_constrained)."""
    beta0 = np.asarray(beta0, dtype=float)
    q_base = np.atleast_1d(np.asarray(q_base, dtype=float))
    joints = np.atleast_2d(joints)
    total_mass = robot.nominal_mass if total_mass is None else float(total_mass)
    noise = noise or NoiseModel()
    info = {'method': method, 'poses': int(len(q_base))}
    if method in ('paper-gd', 'paper-gd-mass'):
        e = make_estimator(method, beta0, robot=robot, eta=eta) if method == 'paper-gd' else \
            make_estimator(method, beta0, robot=robot, eta=eta, total_mass=total_mass)
        for qb, jt in zip(q_base, joints):
            e.update_pose(robot, qb, jt)
        info['converged_paper_rule'] = bool(e.converged)
        return e.beta, info
    if method not in ('map', 'map-online'):
        raise ValueError(f'unknown method {method!r}; choose one of {ESTIMATORS}')
    prior = physical_prior_std(robot, beta0, mass_frac=mass_frac, com_std=com_std)
    A, b = equality_constraints(robot, total_mass)
    if method == 'map-online':
        e = MAPOnline(robot, beta0, prior, noise, A, b)
        for qb, jt in zip(q_base, joints):
            e.update_pose(robot, qb, jt)
        info['covariance_trace'] = float(np.trace(e.covariance))
        info['relinearizations'] = e.relinearizations
        return e.beta, info
    beta, cov, lin = map_gauss_newton(robot, q_base, joints, beta0, prior, noise, A, b)
    info['covariance_trace'] = float(np.trace(cov))
    if physical:
        G, h = inequality_constraints(robot)
        info['inequality_qp'] = bool(np.any(G @ beta < h - 1e-12))
        if info['inequality_qp']:
            rows, y, var = balanced_pose_rows(robot, q_base, joints, lin, noise)
            beta = map_constrained(beta0, prior, rows, y, var, A, b, G, h, beta_start=beta)
    return beta, info


def cross_validate(method, robot, q_base, joints, beta0, folds=10, seed=0, **kw):
    """k-fold CV of `fit` on balanced poses: predictions x_com = phi^T beta on each held-out record
    and the pitch error atan2(x_com, psi^T beta). Training records keep their order."""
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
        beta, _ = fit(method, robot, q_base[tr], joints[tr], beta0, **kw)
        pred[f] = P[f] @ beta
        pitch[f] = np.arctan2(pred[f], Psi[f] @ beta)
    return pred, pitch
