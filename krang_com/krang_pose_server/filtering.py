"""Meta-learned pose filtering: the paper's Algorithm 1 and better criteria.

Algorithm 1 (paper §II-B), criterion `paper-l1`, exactly:
    repeat
        i* = argmax_i sum_k |Phi_i^T beta_k|          (over the poses still in the pool)
        append pose i*; phi* = Phi_i*
        beta_k <- beta_k - eta phi* phi*^T beta_k   for every k
        remove pose i* from the pool
    until |phi*^T beta_k| < x_tol for all k, for the last `window` iterations
Details taken from the authors' code (18c filter_training_set.cpp): the error of the chosen pose is
taken before its update; ties in the argmax go to the LAST pose in pool order (`>=`); the pose that
completes the window is part of the output.

Speed. Recomputing E = Phi^T B (n_poses x n_betas) each iteration costs n_poses*n_betas*92 flops
(1e9 at the paper's scale, 22,000 x 500 x 92) and even keeping E and correcting it by the rank-one
update E <- E - (Phi k)(phi*^T B) still touches all n_poses*n_betas entries (11e6) per iteration.
Here only the betas B (92 x n_betas) are updated and a pose's score s_i = ||B^T phi_i||_1 is
evaluated exactly when it can still be the maximum, judged by two upper bounds that cost O(n_poses)
per step:
- the squared row norm q_i = ||B^T phi_i||_2^2 = phi_i^T C phi_i with C = B B^T, kept exactly by
  the rank-one algebra (B' = B - k e*^T, e* = B^T phi*, g = Phi k, w = C phi*, h = Phi w, c =
  phi*^T w):
      q_i' = q_i - 2 g_i h_i + g_i^2 c,     C' = C - k w^T - w k^T + c k k^T
  and s_i <= sqrt(n_betas q_i);
- since row i changed by -g_i e* at each step, s_i <= s_i(last exact evaluation) + sum |g_i|
  ||e*||_1.
Poses are evaluated in decreasing bound order until the best exact score beats every remaining
bound (ties included), so the argmax is the one of the straightforward algorithm. Per step this is
two matvecs with Phi plus a few hundred exact rows instead of 11e6 entries.

Other criteria (same loop, same stop rule):
- `squared`: i* = argmax_i sum_k (Phi_i^T beta_k)^2 = q_i, which the rank-one algebra keeps
  exactly.
- `d-optimal`: greedy D-optimal design, i* = argmax_i log det(A + phi_i phi_i^T / r_i) - log det A
  = argmax_i log(1 + phi_i^T A^-1 phi_i / r_i), with A the information matrix (prior precision plus
  the chosen poses). A^-1 is updated by Sherman-Morrison and v_i = phi_i^T A^-1 phi_i by one
  matvec:
      u = A^-1 phi*, v_i' = v_i - (phi_i^T u)^2 / (r* + v*).
  log det is submodular, so greedy is within (1 - 1/e) of the best design (notes §3).

The betas are moved either by the paper's GD (`learner='gd'`: k = eta phi*) or by the MAP/Kalman
update of krang_com_estimator (`learner='map'`: k = Sigma phi* / (phi*^T Sigma phi* + r*), the same
Sigma = A^-1 as D-optimal), so the stop rule measures the learner the poses are meant for.

`filter_straightforward` recomputes everything each iteration, literally as written in Algorithm 1;
it exists for the tests and the benchmark only.
"""

import time
from dataclasses import dataclass

import numpy as np

from krang_model.config import load_config

CRITERIA = ('paper-l1', 'squared', 'd-optimal')
LEARNERS = ('gd', 'map')


def filter_config():
    return dict(load_config('poses.yaml')['pose_server']['ros__parameters']['filter'])


@dataclass
class FilterResult:
    selected: np.ndarray  # pool indices, in the order chosen
    max_error: np.ndarray  # per step: max_k |phi*^T beta_k| before the update (m)
    mean_error: np.ndarray  # per step: mean_k |phi*^T beta_k| before the update (m)
    converged: bool  # the stop rule fired (else the pool or max_poses ran out)
    seconds: float
    criterion: str
    learner: str
    betas: np.ndarray  # (n_betas, n_beta) after the last update
    evaluations: int = 0  # exact row evaluations (fast paper-l1 / squared)


class _Setup:
    """Argument checking and defaults shared by the fast and the straightforward
    implementations."""

    def __init__(
        self, phi, betas, criterion, eta, x_tol, window, max_poses, learner, prior_cov, noise_var
    ):
        cfg = filter_config()
        self.criterion = criterion or cfg['criterion']
        if self.criterion not in CRITERIA:
            raise ValueError(f'criterion must be one of {CRITERIA}, not {self.criterion!r}')
        self.learner = learner or ('map' if self.criterion == 'd-optimal' else 'gd')
        if self.learner not in LEARNERS:
            raise ValueError(f'learner must be one of {LEARNERS}, not {self.learner!r}')
        if self.criterion == 'paper-l1' and self.learner != 'gd':
            raise ValueError('paper-l1 is Algorithm 1: its learner is the paper GD')
        self.phi = np.ascontiguousarray(phi, dtype=float)
        betas = np.atleast_2d(np.asarray(betas, dtype=float))
        if betas.shape[1] != self.phi.shape[1]:
            raise ValueError(f'betas have {betas.shape[1]} entries, phi has {self.phi.shape[1]}')
        self.B = np.ascontiguousarray(betas.T)  # (n_beta, n_betas)
        self.eta = float(cfg['eta'] if eta is None else eta)
        self.x_tol = float(cfg['x_tol_m'] if x_tol is None else x_tol)
        self.window = int(cfg['window'] if window is None else window)
        n = len(self.phi)
        self.max_poses = n if max_poses is None else min(int(max_poses), n)
        need_sigma = self.criterion == 'd-optimal' or self.learner == 'map'
        self.sigma = None
        self.r = None
        if need_sigma:
            if prior_cov is None:
                ridge = float(cfg.get('d_optimal_ridge', 1e-6))
                prior_cov = np.eye(self.phi.shape[1]) / ridge
            prior_cov = np.asarray(prior_cov, dtype=float)
            self.sigma = np.diag(prior_cov).copy() if prior_cov.ndim == 1 else prior_cov.copy()
            if self.sigma.ndim == 1:
                self.sigma = np.diag(self.sigma)
            nv = 1e-6 if noise_var is None else noise_var
            self.r = np.broadcast_to(np.asarray(nv, dtype=float), (n,)).copy()

    def step(self, i, phi_star):
        """Sherman-Morrison update of Sigma = A^-1 (when kept) and the learner's gain k, for
        B <- B - k e*^T. Returns (k, u = Sigma phi* before the update, r* + phi*^T u)."""
        u = denom = None
        if self.sigma is not None:
            u = self.sigma @ phi_star
            denom = float(phi_star @ u + self.r[i])
            self.sigma -= np.outer(u, u) / denom
            self.sigma = 0.5 * (self.sigma + self.sigma.T)
        k = self.eta * phi_star if self.learner == 'gd' else u / denom
        return k, u, denom


def _stop(max_errors, x_tol, window):
    return len(max_errors) >= window and max(max_errors[-window:]) < x_tol


def _pick_last(scores, idx):
    """argmax with ties to the largest pool index (the authors' `>=` scan)."""
    best = scores.max()
    return int(idx[scores == best].max()), best


def filter_poses(
    phi,
    betas,
    criterion=None,
    eta=None,
    x_tol=None,
    window=None,
    max_poses=None,
    learner=None,
    prior_cov=None,
    noise_var=None,
    progress=None,
):
    """Select poses from the pool rows of `phi` (n_poses, n_beta) for the hypotheses `betas`
    (n_betas, n_beta). Returns a FilterResult; `progress()` is called once per selected pose."""
    t0 = time.perf_counter()
    s = _Setup(phi, betas, criterion, eta, x_tol, window, max_poses, learner, prior_cov, noise_var)
    P, B = s.phi, s.B
    n, nb = len(P), B.shape[1]
    active = np.ones(n, dtype=bool)
    selected, max_err, mean_err = [], [], []
    evaluations = 0
    converged = False

    use_rows = s.criterion in ('paper-l1', 'squared')
    if use_rows:
        E = P @ B
        score = np.abs(E).sum(1) if s.criterion == 'paper-l1' else np.einsum('ij,ij->i', E, E)
        q = np.einsum('ij,ij->i', E, E)
        del E
        C = B @ B.T
        tri = np.zeros(n)  # L1 triangle slack since the last exact evaluation
        q_scale = float(q.max()) if n else 1.0
    else:
        v = np.einsum('ij,jk,ik->i', P, s.sigma, P)

    while len(selected) < s.max_poses:
        if use_rows:
            if s.criterion == 'paper-l1':
                ub = np.minimum(score + tri, np.sqrt(nb * np.maximum(q, 0.0)))
            else:
                ub = q.copy()
            ub = ub * (1.0 + 1e-9) + 1e-12 * (
                q_scale if s.criterion == 'squared' else np.sqrt(nb * q_scale)
            )
            ub[~active] = -np.inf
            i, evals = _lazy_argmax(P, B, ub, score, q, tri, s.criterion)
            evaluations += evals
        else:
            gain = np.where(active, v / s.r, -np.inf)
            i = int(np.flatnonzero(gain == gain.max()).max())
        phi_star = P[i]
        e = phi_star @ B
        selected.append(i)
        max_err.append(float(np.abs(e).max()))
        mean_err.append(float(np.abs(e).mean()))
        k, u, denom = s.step(i, phi_star)
        if s.criterion == 'd-optimal':
            v -= (P @ u) ** 2 / denom
        if use_rows:
            w = C @ phi_star
            c = float(phi_star @ w)
            gh = P @ np.column_stack([k, w])
            g, h = gh[:, 0], gh[:, 1]
            q += -2.0 * g * h + g * g * c
            tri += np.abs(g) * float(np.abs(e).sum())
            C += -np.outer(k, w) - np.outer(w, k) + c * np.outer(k, k)
            if s.criterion == 'squared':
                score = q
        B -= np.outer(k, e)
        active[i] = False
        if progress:
            progress()
        if _stop(max_err, s.x_tol, s.window):
            converged = True
            break
    return FilterResult(
        np.array(selected, dtype=int),
        np.array(max_err),
        np.array(mean_err),
        converged,
        time.perf_counter() - t0,
        s.criterion,
        s.learner,
        B.T.copy(),
        evaluations,
    )


def _lazy_argmax(P, B, ub, score, q, tri, criterion, first=16):
    """Exact argmax of the criterion over the active rows, evaluating rows in decreasing
    upper-bound order (in chunks of doubling size) until no remaining bound can reach the best
    exact score (ties included). Updates score/q/tri in place for every evaluated row. Returns
    (index, rows evaluated)."""
    n_active = int(np.isfinite(ub).sum())
    k = min(first, n_active)
    cand = np.argpartition(-ub, k - 1)[:k] if k < len(ub) else np.flatnonzero(np.isfinite(ub))
    evaluated = np.zeros(len(ub), dtype=bool)
    best_i, best = -1, -np.inf
    evals = 0
    chunk = k
    while len(cand):
        E = P[cand] @ B
        sq = np.einsum('ij,ij->i', E, E)
        exact = np.abs(E).sum(1) if criterion == 'paper-l1' else sq
        score[cand] = exact
        q[cand] = sq
        tri[cand] = 0.0
        evaluated[cand] = True
        evals += len(cand)
        i, b = _pick_last(exact, cand)
        if b > best or (b == best and i > best_i):
            best_i, best = i, b
        # every row whose bound can still reach (or tie) the best must be evaluated exactly; take
        # them best bound first, in growing chunks, since a better best prunes the rest
        rest = np.flatnonzero((ub >= best) & ~evaluated)
        chunk *= 2
        if len(rest) > chunk:
            rest = rest[np.argpartition(-ub[rest], chunk - 1)[:chunk]]
        cand = rest
    return best_i, evals


def filter_straightforward(
    phi,
    betas,
    criterion=None,
    eta=None,
    x_tol=None,
    window=None,
    max_poses=None,
    learner=None,
    prior_cov=None,
    noise_var=None,
    progress=None,
):
    """Reference implementation (tests and benchmark only): Algorithm 1 as written, recomputing
    Phi^T beta_k for all remaining poses and removing the chosen pose from Phi every iteration."""
    t0 = time.perf_counter()
    s = _Setup(phi, betas, criterion, eta, x_tol, window, max_poses, learner, prior_cov, noise_var)
    B = s.B
    Phi = s.phi.copy()
    index = np.arange(len(Phi))
    r = s.r.copy() if s.r is not None else None
    selected, max_err, mean_err = [], [], []
    converged = False
    while len(selected) < s.max_poses and len(Phi):
        if s.criterion == 'paper-l1':
            scores = np.abs(Phi @ B).sum(1)
        elif s.criterion == 'squared':
            E = Phi @ B
            scores = (E * E).sum(1)
        else:
            scores = np.einsum('ij,jk,ik->i', Phi, s.sigma, Phi) / r
        j = int(np.flatnonzero(scores == scores.max()).max())  # ties -> last, as `>=`
        i = int(index[j])
        phi_star = Phi[j]
        e = phi_star @ B
        selected.append(i)
        max_err.append(float(np.abs(e).max()))
        mean_err.append(float(np.abs(e).mean()))
        k, _, _ = s.step(i, phi_star)
        B -= np.outer(k, e)
        Phi = np.delete(Phi, j, axis=0)
        index = np.delete(index, j)
        if r is not None:
            r = np.delete(r, j)
        if progress:
            progress()
        if _stop(max_err, s.x_tol, s.window):
            converged = True
            break
    return FilterResult(
        np.array(selected, dtype=int),
        np.array(max_err),
        np.array(mean_err),
        converged,
        time.perf_counter() - t0,
        s.criterion,
        s.learner,
        B.T.copy(),
    )
