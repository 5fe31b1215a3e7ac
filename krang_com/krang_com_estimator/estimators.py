"""The built-in estimators of beta from balanced poses (pure numpy; no rclpy):
- `paper-gd`: the paper's GD, beta <- beta - eta (phi^T beta - y) phi (eta = 300), with the stop
  rule |phi^T beta| < x_tol for the last `window` poses, and the authors' unused mass penalty u.
  `gd_step` is the same step on many betas at once (the experiments' vectorised runs).
- `paper-gd-mass`: the same step followed by the Lagrange-multiplier projection that keeps the
  total mass at M_known (the constraint the paper describes and the authors left off;
  `project_total_mass`).
- `map-online` / `map`: Bayesian MAP with a Gaussian prior N(beta0, diag(s^2)) from physical
  plausibility and hard linear equality constraints (known total mass, wheel CoMs on the axle)
  imposed by conditioning the prior on them. `MAPEstimator` is the linear-Gaussian core: a Kalman
  / recursive least-squares rank-one update of (mean, covariance) from given rows;
  solvers.map_batch solves the same problem in one go with the same result. `MAPOnline` feeds it
  the CoM-angle rows (rows.balanced_pose_rows) and re-linearises (a batch Gauss-Newton pass over
  the poses so far) when the estimate has moved enough to matter; solvers.map_gauss_newton is the
  batch form, which `MAP.fit` uses and `MAPOnline.finalize()` equals. `MAP` adds the bounds of
  physical plausibility (positive masses, each within a stated spread of the URDF's, every CoM
  inside the inflated collision box of its link and within a stated radius of CAD) as a convex
  program when the Gaussian MAP leaves them.
The paper estimators and MAPEstimator also take linear rows (`update_row`, `update_rows`).
"""

import math

import numpy as np

from krang_model.com import phi as phi_fn

from .priors import (
    COM_RADIUS_M,
    MASS_SPREAD,
    com_balls,
    equality_constraints,
    inequality_constraints,
    physical_prior_std,
)
from .registry import Estimator, register_estimator
from .rows import NoiseModel, angle_rows, balanced_pose_rows, offset_rows, pitch_rows
from .solvers import (
    calibrate_scales,
    condition_on_constraints,
    map_constrained,
    map_gauss_newton,
    within_bounds,
)


# ---------------------------------------------------- the paper's GD, one or many betas
def gd_step(betas, rows, eta=300.0, errors=None):
    """The paper's step, in place: beta <- beta - eta e phi, on one beta (n,) or a stack (K, n),
    with one row for all (n,) or one per beta (K, n). e is phi^T beta before the step unless given
    (PaperGD passes its error with the authors' mass penalty). Returns e."""
    if errors is None:
        errors = np.einsum('...j,...j->...', rows, betas)
    betas -= np.asarray(eta * errors)[..., None] * rows
    return errors


def mass_weights(beta0, weights='mass'):
    """Which masses absorb the total-mass projection (project_total_mass): 'mass' in proportion to
    the masses of beta0 (one beta or a stack), 'euclidean' evenly, or given per entry."""
    beta0 = np.asarray(beta0, dtype=float)
    a = np.zeros(beta0.shape[-1])
    a[0::4] = 1.0
    if isinstance(weights, str):
        if weights == 'mass':
            return np.abs(beta0) * a
        if weights == 'euclidean':
            return a.copy()
        raise ValueError(f'weights must be "mass", "euclidean" or an array, not {weights!r}')
    return np.asarray(weights, dtype=float) * a


def project_total_mass(betas, weights, total_mass):
    """The Lagrange-multiplier projection onto sum(m) = total_mass, min (beta'-b)^T W^-1 (beta'-b):
    beta' = b + W a (M - a^T b) / (a^T W a), W = diag(weights) (mass_weights), for one beta or a
    stack (K, n) with its weights."""
    a = np.zeros(np.shape(betas)[-1])
    a[0::4] = 1.0
    if np.ndim(betas) == 1:
        return betas + weights * (total_mass - a @ betas) / (a @ weights)
    return betas + weights * (total_mass - betas @ a)[:, None] / (weights @ a)[..., None]


def gd_stop_count(rows, betas, eta=300.0, x_tol=2e-3, window=10):
    """The paper's GD on every beta along the pose sequence `rows`: the number of poses after which
    its stop rule (max_k |phi^T beta_k| < x_tol for the last `window` poses) fires, or None, and
    the per-step max error."""
    B = np.array(betas, dtype=float)
    run = 0
    max_err = np.empty(len(rows))
    for n, p in enumerate(rows):
        e = gd_step(B, p, eta)
        max_err[n] = np.abs(e).max()
        run = run + 1 if max_err[n] < x_tol else 0
        if run >= window:
            return n + 1, max_err[: n + 1]
    return None, max_err


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

    def _step(self, phi_row, err):
        """gd_step in place, with the authors' mass penalty when u != 0."""
        if self.u:
            err_u = err + self.u * (self.mass_indicator @ self._beta - self.total_mass)
            gd_step(self._beta, phi_row + self.u * self.mass_indicator, self.eta, err_u)
        else:
            gd_step(self._beta, phi_row, self.eta, err)

    def _update(self, phi_row, y, noise_var, err):
        self._step(phi_row, err)

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
        self._wa = mass_weights(beta0, weights)
        if total_mass is None and robot is not None:
            total_mass = robot.nominal_mass
        super().__init__(robot, beta0, eta=eta, x_tol=x_tol, window=window, total_mass=total_mass)

    def reset(self, beta0=None):
        super().reset(beta0)
        self._beta = project_total_mass(self._beta, self._wa, self.total_mass)

    def _update(self, phi_row, y, noise_var, err):
        self._step(phi_row, err)
        self._beta = project_total_mass(self._beta, self._wa, self.total_mass)


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
    all poses (map_gauss_newton), then, with physical=True, the constrained MAP if the Gaussian
    MAP leaves the plausible region (map_constrained, re-linearised until it settles): positive
    masses, each within mass_spread of the URDF's (priors.mass_bounds; None: no such bound),
    each CoM inside its link's inflated collision box and within com_radius m of CAD
    (priors.com_balls; None: no such bound). Online: map-online.

    calibrate=True: the noise and prior scales (sigma_pitch, mass_frac, com_std) come from the
    training poses by evidence maximisation (calibrate_scales) before the fit, mass_frac at most
    mass_spread / 2 (when given). pitch_offset_std
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
        mass_spread=MASS_SPREAD,
        com_radius=COM_RADIUS_M,
    ):
        self.physical = physical
        self.mass_spread = mass_spread
        self.com_radius = com_radius
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
                bounds=self._calibration_bounds(),
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
        if self.physical:
            beta, lin, info['inequality_qp'] = self._bounded(q_base, joints, beta, lin)
        if self.pitch_offset_std is not None:
            self.pitch_offset = float(beta[n])
            self.pitch_offset_std_post = float(math.sqrt(cov[n, n]))
            info.update(
                pitch_offset_rad=self.pitch_offset, pitch_offset_std_rad=self.pitch_offset_std_post
            )
            q_base = q_base - self.pitch_offset  # the poses as the model now sees them
            beta, cov, lin = beta[:n], cov[:n, :n], lin[:n]
        info['covariance_trace'] = float(np.trace(cov))
        self.q = [float(v) for v in q_base]
        self.joints = [j.copy() for j in np.asarray(joints, dtype=float)]
        self.sigmas = [math.nan] * len(self.q)
        self.n_updates = len(q_base)
        self._set_posterior(beta, cov, lin)
        return self.beta, info

    def _calibration_bounds(self):
        """The calibration searches only mass stds that keep the plausible mass range at two of
        them or more (mass_frac <= mass_spread / 2): a wider prior would put most of its weight
        on masses the plausible region excludes."""
        if self.mass_spread is None:
            return None
        return {'mass_frac': (0.0, self.mass_spread / 2)}

    def _bounded(self, q_base, joints, beta, lin, iterations=5):
        """(beta, lin, bounded?): the Gaussian MAP if it is inside the plausible region, else the
        constrained MAP, its rows re-linearised at each solution until it moves less than 1e-6
        of |beta0|. With a pitch offset (last entry of beta) the offset is solved with beta, so
        where the bounds stop the masses it can take what the data ask. The covariance stays the
        Gaussian posterior's."""
        n = self.robot.n_beta
        G, h = inequality_constraints(self.robot, mass_spread=self.mass_spread)
        balls = com_balls(self.robot, self.com_radius) if self.com_radius is not None else None
        if within_bounds(beta[:n], G, h, balls):
            return beta, lin, False
        beta0, std, A, rows_fn = self.beta0, self.prior_std, self.A, angle_rows
        if len(beta) > n:
            beta0, std = np.append(beta0, 0.0), np.append(std, self.pitch_offset_std)
            A, G = (np.column_stack([M, np.zeros(len(M))]) for M in (A, G))
            rows_fn = offset_rows
        P, Psi = phi_fn(self.robot, q_base, joints), pitch_rows(self.robot, q_base, joints)
        scale = np.abs(self.beta0).max()
        for _ in range(iterations):
            rows, y, var = rows_fn(P, Psi, lin[:n], self.noise)
            beta = map_constrained(beta0, std, rows, y, var, A, self.b, G, h, balls=balls)
            step = np.abs(beta - lin).max()
            lin = beta
            if step < 1e-6 * scale:
                break
        return beta, lin, True
