"""The MAP solvers: the linear-Gaussian MAP in one solve (null-space form), its Gauss-Newton
iteration on the CoM-angle rows, the evidence and the calibration of the noise and prior scales
by evidence maximisation, and the inequality-constrained QP."""

import math

import numpy as np
from scipy.linalg import cho_solve
from scipy.optimize import minimize

from krang_model.com import phi as phi_fn

from .priors import physical_prior_std
from .rows import NoiseModel, angle_rows, offset_rows, pitch_rows


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
    bounds=None,
):
    """Noise and prior scales from the data by evidence maximisation (type-II maximum
    likelihood): the pitch noise sigma_pitch and the prior's mass_frac and com_std
    (physical_prior_std) that maximise log_evidence, alternating with the Gauss-Newton MAP they
    give (the linearisation point), within CALIBRATION_BOUNDS, narrowed by `bounds` (same keys;
    e.g. MAP keeps mass_frac within half its plausible mass spread). Per-pose sigma_pitch values,
    if given, are added in quadrature (NoiseModel.pitch_std). Returns a dict (sigma_pitch_rad,
    mass_frac, com_std_m, log_evidence)."""
    q_meas = np.atleast_1d(np.asarray(q_meas, dtype=float))
    joints = np.atleast_2d(joints)
    P, Psi = phi_fn(robot, q_meas, joints), pitch_rows(robot, q_meas, joints)
    start = start or {'sigma_pitch_rad': math.radians(0.1), 'mass_frac': 0.1, 'com_std_m': 0.03}
    keys = ('sigma_pitch_rad', 'mass_frac', 'com_std_m')
    limits = {k: tuple(CALIBRATION_BOUNDS[k]) for k in keys}
    for k, (lo, hi) in (bounds or {}).items():
        limits[k] = (max(lo, limits[k][0]), min(hi, limits[k][1]))
    bounds = [tuple(np.log(limits[k])) for k in keys]
    theta = np.clip(np.log([start[k] for k in keys]), *np.array(bounds).T)

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
    balls=None,
):
    """MAP with the equality constraints A beta = b AND the inequalities G beta >= h, and with
    `balls` = (ids, centres, radius) (priors.com_balls) every listed body's CoM within `radius`
    of its centre: (r m)^2 - |m c - m centre|^2 >= 0, convex for m > 0. A convex program, solved
    on the null space of A, whitened by the posterior information (so SLSQP sees the identity),
    over a working set: the constraints the start violates, then those the solution violates,
    until none is. Returns beta."""
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
    G = np.zeros((0, n)) if G is None else np.atleast_2d(G)
    h = np.zeros(0) if h is None else np.atleast_1d(h)
    ball = _BallConstraints(balls, n)
    if within_bounds(start, G, h, balls):
        return start
    p0inv = 1.0 / np.asarray(prior_std, dtype=float) ** 2
    W = Phi / r[:, None]
    Z = null_space(A, n)
    H = Z.T @ (p0inv[:, None] * Z) + (Phi @ Z).T @ (W @ Z)
    g = Z.T @ (p0inv * (beta0 - start) + W.T @ (y - Phi @ start))
    # z = T u with T = L^-T (H = L L^T): f(u) = 1/2 |u|^2 - (T^T g)^T u; beta = start + Zt u
    L = np.linalg.cholesky(0.5 * (H + H.T))
    Zt = Z @ np.linalg.inv(L).T
    gu = np.linalg.solve(L, g)
    lin_set = np.flatnonzero(G @ start < h - 1e-12)
    ball_set = np.flatnonzero(ball.value(start) < 0)
    u = np.zeros(Zt.shape[1])
    for _ in range(20):
        cons = []
        if len(lin_set):
            GZ, hz = G[lin_set] @ Zt, h[lin_set] - G[lin_set] @ start
            cons.append(
                {
                    'type': 'ineq',
                    'fun': lambda u, GZ=GZ, hz=hz: GZ @ u - hz,
                    'jac': lambda u, GZ=GZ: GZ,
                }
            )
        if len(ball_set):
            cons.append(
                {
                    'type': 'ineq',
                    'fun': lambda u, k=ball_set: ball.value(start + Zt @ u, k),
                    'jac': lambda u, k=ball_set: ball.jacobian(start + Zt @ u, k) @ Zt,
                }
            )
        res = minimize(
            lambda u: 0.5 * u @ u - gu @ u,
            u,
            jac=lambda u: u - gu,
            constraints=cons,
            method='SLSQP',
            options={'maxiter': 500, 'ftol': 1e-14},
        )
        u = res.x
        beta = start + Zt @ u
        more_lin = np.setdiff1d(np.flatnonzero(G @ beta < h - 1e-9), lin_set)
        more_ball = np.setdiff1d(np.flatnonzero(ball.value(beta) < -1e-9), ball_set)
        if not len(more_lin) and not len(more_ball):
            break
        lin_set = np.union1d(lin_set, more_lin)
        ball_set = np.union1d(ball_set, more_ball)
    return beta


def within_bounds(beta, G=None, h=None, balls=None):
    """True if G beta >= h and every CoM of `balls` lies within its radius (map_constrained)."""
    beta = np.asarray(beta, dtype=float)
    inside = G is None or bool(np.all(np.atleast_2d(G) @ beta >= np.atleast_1d(h) - 1e-12))
    return inside and bool(np.all(_BallConstraints(balls, len(beta)).value(beta) >= 0))


class _BallConstraints:
    """(r m_i)^2 - |m_i c_i - m_i centre_i|^2 >= 0 for the bodies of priors.com_balls, and its
    Jacobian in beta; none when balls is None."""

    def __init__(self, balls, n):
        self.n = n
        if balls is None:
            self.ids, self.centres, self.radius = np.zeros(0, int), np.zeros((0, 3)), 0.0
        else:
            ids, centres, self.radius = balls
            self.ids, self.centres = np.asarray(ids, int), np.asarray(centres, float)

    def _parts(self, beta, k):
        ids = self.ids if k is None else self.ids[k]
        cen = self.centres if k is None else self.centres[k]
        m = beta[4 * ids]
        d = beta[4 * ids[:, None] + np.arange(1, 4)] - m[:, None] * cen
        return ids, cen, m, d

    def value(self, beta, k=None):
        _, _, m, d = self._parts(beta, k)
        return (self.radius * m) ** 2 - (d * d).sum(1)

    def jacobian(self, beta, k=None):
        ids, cen, m, d = self._parts(beta, k)
        J = np.zeros((len(ids), self.n))
        rows = np.arange(len(ids))
        J[rows, 4 * ids] = 2 * self.radius**2 * m + 2 * (d * cen).sum(1)
        J[rows[:, None], 4 * ids[:, None] + np.arange(1, 4)] = -2 * d
        return J
