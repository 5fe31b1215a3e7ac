"""Name the missing effect: fit every candidate of the library (and small combinations), pick by
improvement on HELD-OUT data with a minimum effect size, report the value with its uncertainty and
the evidence, or ``none``.

Procedure (``name_effects``):

1. Scales. The nominal model's residuals on the fitting windows off the caster (the sitting
   windows are fitted too, but the caster holds the body still) give one robust whitening scale per
   signal and horizon point, sqrt(median(r^2) / 0.455), so pitch, pitch rate, wheel angle and wheel
   rate count alike and a few outlying windows do not set the yardstick.
2. Folds. Windows are grouped in blocks of ``block_s`` seconds; block b belongs to fold b mod K.
   Interleaved blocks keep every phase in every fold, and a window's neighbours (which share its
   data) mostly sit in its own block.
3. Fits. A 9-point scan over each effect's bounds gives the start; each candidate is then fitted on
   all windows (value, uncertainty) by a bounded Levenberg-Marquardt on the soft-L1 loss
   2 (sqrt(1 + z^2) - 1) of the whitened residuals z (finite-difference Jacobians; all candidates
   advance in the same batched prediction), and on each fold's training windows starting from the
   full-data optimum; each fold fit predicts the fold's held-out windows.
4. Evidence: improvement = 1 - (held-out loss with the effect) / (held-out nominal loss);
   t = paired t over blocks of log(loss_nominal_b / loss_candidate_b), a test over blocks that does
   not pretend overlapping windows are independent (and, on log ratios, is not dominated by the
   most excited blocks).
5. Selection: an effect (alone, or added to the accepted set) is accepted if it removes at
   least ``min_improvement`` of the (remaining) held-out loss AND either t >= ``min_t`` or the
   evidence-weighted t (blocks weighted by how much the effect changes the predictions there, see
   ``_compare``) is >= ``min_t`` over at least ``min_weighted_blocks`` effective blocks. Forward up
   to ``max_effects`` (partners ranked by the better of a conditional scan, whose grids hold each
   effect's zero and its single-fit value, and a joint Gauss-Newton step that lets the accepted
   values move with the partner, ``_joint_step``),
   with a backward step once a third effect enters (``_drop_redundant``). With a long record an
   information criterion alone admits spurious terms (notes/identification.md §4); the minimum
   effect size on held-out data does not. When no partner passes and the accepted set misses the
   pitch on the caster, the sitting route (``_admit_by_sitting``) weighs that static evidence
   against its own run-to-run noise instead of as the block or two the sitting lasts.
6. Uncertainty: the larger of the cluster-robust sandwich (``cluster_s`` clusters) and the
   delete-a-fold jackknife of the fold fits (``_uncertainty``), combined with the discretisation
   error of the replay (``refine_step``, run by ``krang_discrepancy.report``).
7. Consistency: ``per_record_values`` / ``per_third_values`` refit the selection per record and
   per third of the records (``split_values``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .replay import Replay, gap_metrics
from krang_model.effects import Effect, ModelTerms, apply_effects, library
from .verdict import SITTING_TOL, sitting_offset


@dataclass
class NamingConfig:
    folds: int = 2
    block_s: float = 2.0
    min_improvement: float = 0.10  # minimum share of the held-out loss an effect must remove
    min_t: float = 3.0  # minimum paired t over held-out blocks
    max_effects: int = 3
    combo_candidates: int = 4  # partners tried for a combination (best singles first)
    cluster_s: float = 2.0  # = the block: errors stay correlated over ~1-2 s
    min_weighted_blocks: float = 4.0  # effective blocks the evidence-weighted t needs
    max_nfev: int = 25  # Levenberg-Marquardt iterations per fit


@dataclass
class Fit:
    """One fitted candidate set (a single effect or a combination)."""

    effects: list
    values: np.ndarray
    uncertainty: np.ndarray
    train_loss: float  # mean whitened loss on all fitting windows at the fit
    heldout_loss: np.ndarray  # per active window (NaN elsewhere)
    fold_values: np.ndarray  # (K, p)
    improvement: float = math.nan  # vs the reference (nominal, or the smaller set)
    t: float = math.nan
    blocks_better: float = math.nan  # share of held-out blocks where it is better
    t_weighted: float = math.nan  # paired t with blocks weighted by the effect's visibility
    weighted_blocks: float = math.nan  # effective number of blocks of that test
    at_bound: bool = False
    nfev: int = 0
    seconds: float = 0.0
    reference: str = 'nominal'

    @property
    def key(self):
        return '+'.join(e.key for e in self.effects)

    def summary(self, base=None) -> dict:
        out = {
            'candidate': self.key,
            'improvement': self.improvement,
            't': self.t,
            't_weighted': self.t_weighted,
            'weighted_blocks': self.weighted_blocks,
            'blocks_better': self.blocks_better,
            'at_bound': self.at_bound,
            'reference': self.reference,
            'train_loss': self.train_loss,
            'heldout_loss': float(np.nanmean(self.heldout_loss)),
            'effects': [],
        }
        for e, v, u in zip(self.effects, self.values, self.uncertainty):
            dv, unit = e.display(float(v), base)
            out['effects'].append(
                {
                    'effect': e.name,
                    'key': e.key,
                    'value': dv,
                    'unit': unit,
                    'uncertainty': float(u) * e.display_scale(base),
                    'parameter': float(v),
                    **({'detail': e.detail} if e.detail else {}),
                }
            )
        return out


@dataclass
class NamingResult:
    selected: Fit | None
    singles: list
    combos: list
    nominal_heldout: np.ndarray
    scales: np.ndarray
    config: NamingConfig
    folds: np.ndarray
    blocks: np.ndarray
    timing: dict = field(default_factory=dict)

    @property
    def name(self):
        return 'none' if self.selected is None else '+'.join(e.name for e in self.selected.effects)


def _soft_l1(z2):
    return 2.0 * (np.sqrt(1.0 + z2) - 1.0)


@dataclass
class _Job:
    """One bounded robust least-squares problem: `effects` fitted on the windows `wset`."""

    effects: list
    wset: int
    x: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    h: np.ndarray
    cost: float = math.inf
    grad: np.ndarray | None = None
    hess: np.ndarray | None = None
    jac: np.ndarray | None = None
    res: np.ndarray | None = None
    lam: float = 1e-3
    step: np.ndarray | None = None
    done: bool = False
    iters: int = 0
    nfev: int = 0


def _interior(x, lo, hi, margin=0.01):
    """x moved at least `margin` of the range inside the bounds (a fit started on a bound learns
    nothing from a one-sided finite difference there)."""
    span = hi - lo
    return np.clip(np.asarray(x, float), lo + margin * span, hi - margin * span)


def _fd_steps(effects, x, lo, hi):
    h = np.array([0.02 * e.scale for e in effects])
    return np.where(x + h > hi, -h, h)


def _evaluate(replay, base, jobs, wsets, need_jac=True):
    """Whitened residuals (and forward-difference Jacobians) of every job at its trial point;
    one predict call per window set."""
    by_set = {}
    for j in jobs:
        by_set.setdefault(j.wset, []).append(j)
    for ws, js in by_set.items():
        w = wsets[ws]
        terms, owner = [], []
        for j in js:
            pts = [j.trial] + (
                [j.trial + np.eye(len(j.trial))[k] * j.h[k] for k in range(len(j.trial))]
                if need_jac
                else []
            )
            for x in pts:
                terms.append(apply_effects(base, j.effects, x))
            owner.append(len(pts))
        pred = replay.predict(terms, w)
        z = ((replay.measured[w][None] - pred) / replay.scales).reshape(len(terms), -1)
        k = 0
        for j, n in zip(js, owner):
            j.trial_res = z[k]
            j.trial_jac = ((z[k + 1 : k + n] - z[k]) / j.h[:, None]).T if need_jac else None
            j.nfev += n
            k += n


def _cost_grad_hess(res, jac):
    z2 = res**2
    cost = float(np.sum(_soft_l1(z2)))
    if jac is None:
        return cost, None, None
    w1 = 1.0 / np.sqrt(1.0 + z2)  # rho'(z^2): gradient weights
    w2 = w1**3  # Gauss-Newton curvature weights
    grad = jac.T @ (w1 * res)
    hess = (jac * w2[:, None]).T @ jac
    return cost, grad, hess


def _newton(job):
    hs = job.hess + job.lam * np.diag(np.maximum(np.diag(job.hess), 1e-12))
    try:
        step = -np.linalg.solve(hs, job.grad)
    except np.linalg.LinAlgError:
        step = -job.grad / np.maximum(np.diag(hs), 1e-12)
    return np.clip(job.x + step, job.lo, job.hi) - job.x


def _batched_fit(replay, base, jobs, wsets, max_iter=25, tol=1e-3, evaluate=None):
    """Bounded Levenberg-Marquardt on the soft-L1 loss, all jobs advancing together. `evaluate`
    (default ``_evaluate``) sets each job's trial_res and trial_jac at its trial point."""
    _evaluate_jobs = evaluate or _evaluate
    for j in jobs:
        j.trial = j.x.copy()
    _evaluate_jobs(replay, base, jobs, wsets)
    for j in jobs:
        j.res, j.jac = j.trial_res, j.trial_jac
        j.cost, j.grad, j.hess = _cost_grad_hess(j.res, j.jac)
        j.step = _newton(j)
    for _ in range(max_iter):
        live = [j for j in jobs if not j.done]
        if not live:
            break
        for j in live:
            j.trial = j.x + j.step
        _evaluate_jobs(replay, base, live, wsets)
        for j in live:
            j.iters += 1
            cost, grad, hess = _cost_grad_hess(j.trial_res, j.trial_jac)
            small = np.all(np.abs(j.step) <= tol * np.array([e.scale for e in j.effects]))
            if cost <= j.cost:
                rel = (j.cost - cost) / max(j.cost, 1e-300)
                j.x, j.cost, j.grad, j.hess = j.trial.copy(), cost, grad, hess
                j.res, j.jac = j.trial_res, j.trial_jac
                j.lam = max(j.lam / 3.0, 1e-9)
                j.step = _newton(j)
                if small or rel < 1e-10:
                    j.done = True
            else:
                j.lam *= 5.0
                j.step = _newton(j)
                if small or j.lam > 1e8:
                    j.done = True
    return jobs


def _cluster_cov(jac, res, win_cluster, n_per_window):
    """Cluster-robust sandwich covariance of the soft-L1 M-estimate (whitened residuals `res`,
    Jacobian `jac`): A = sum w_i J_i J_i', w = (1 + z^2)^-1.5 (the Gauss-Newton Hessian of the
    loss), scores g_i = z_i (1 + z_i^2)^-0.5 J_i summed per cluster, cov = A^-1 B A^-1."""
    w = (1.0 + res**2) ** -1.5
    a = (jac * w[:, None]).T @ jac
    try:
        ainv = np.linalg.inv(a)
    except np.linalg.LinAlgError:
        return np.full((jac.shape[1], jac.shape[1]), np.nan)
    g = jac * (res / np.sqrt(1.0 + res**2))[:, None]
    cl = np.repeat(win_cluster, n_per_window)
    uniq, inv = np.unique(cl, return_inverse=True)
    gsum = np.zeros((uniq.size, jac.shape[1]))
    np.add.at(gsum, inv, g)
    c = uniq.size
    b = gsum.T @ gsum * (c / max(c - 1, 1))
    return ainv @ b @ ainv


def start_value(effect: Effect, base: ModelTerms) -> float:
    """The parameter value at which the effect leaves `base` unchanged."""
    if effect.name == 'wheel_radius':
        return base.drive.wheel_radius
    if effect.name == 'drive_current_limit':
        return base.drive.current_limit
    return effect.nominal_value


def scan_grid(effect: Effect, base: ModelTerms, n: int = 9, extra=()) -> np.ndarray:
    """n points over the effect's bounds plus its zero (the value that leaves `base` unchanged)
    and any `extra` points inside the bounds."""
    lo, hi = effect.bounds
    grid = np.linspace(lo, hi, n)
    more = [float(v) for v in extra if lo <= v <= hi]
    return np.unique(np.append(grid, [start_value(effect, base), *more]))


def _scan(replay, base, effects, windows, n=9, with_loss=False, extra=None):
    """Best point of a coarse grid over each effect's bounds, all effects in one batched
    prediction: the start of each single-effect fit, so that no fit begins far from its optimum
    (the actuation-delay loss, for one, is not convex over its whole range). `base` may already
    carry accepted effects (a conditional scan). With with_loss, also the best mean loss of each.
    """
    w = np.flatnonzero(windows)
    terms = []
    grids = []
    for i, e in enumerate(effects):
        # the grid holds the effect's own zero (the value that leaves `base` unchanged): without
        # it an effect whose zero falls between grid points (the wheel radius) starts every
        # conditional scan worse than doing nothing and loses to partners that have theirs
        grid = scan_grid(e, base, n, () if extra is None else extra[i])
        grids.append(grid)
        terms += [apply_effects(base, [e], [g]) for g in grid]
    pred = replay.predict(terms, w)
    flat = replay.window_loss(replay.measured[w][None] - pred).mean(axis=1)
    loss = np.split(flat, np.cumsum([g.size for g in grids])[:-1])
    best = [float(g[int(np.argmin(v))]) for g, v in zip(grids, loss)]
    return (best, [float(v.min()) for v in loss]) if with_loss else best


def _joint_step(replay, base, selected: Fit, partners, windows, lengths=(1.0, 4.0, 16.0, 64.0)):
    """For each partner (a single-effect Fit), a Gauss-Newton step of the accepted effects plus
    the partner, from the accepted values and the partner's zero, and the best mean window loss
    along it: ([values], [loss]). The step's length is searched (``lengths`` x the step): the
    caster's stiff, unilateral contact makes the local curvature of the sitting windows far larger
    than the loss's over a physical change (a 0.01 rad IMU bias with the radius it frees: 40x),
    so the Gauss-Newton step points the right way but falls short. One batched prediction for the
    shared Jacobian columns, one for the points along the steps."""
    w = np.flatnonzero(windows)
    effs, x = list(selected.effects), np.asarray(selected.values, float)
    lo = np.array([e.bounds[0] for e in effs], float)
    hi = np.array([e.bounds[1] for e in effs], float)
    h = _fd_steps(effs, x, lo, hi)
    terms = [apply_effects(base, effs, x)]
    terms += [apply_effects(base, effs, x + np.eye(x.size)[k] * h[k]) for k in range(x.size)]
    starts, hp = [], []
    for f in partners:
        e = f.effects[0]
        x0 = float(start_value(e, base))
        step = float(_fd_steps([e], np.array([x0]), *np.array([e.bounds]).T)[0])
        starts.append(x0)
        hp.append(step)
        terms.append(apply_effects(base, effs + [e], np.append(x, x0 + step)))
    z = ((replay.measured[w][None] - replay.predict(terms, w)) / replay.scales).reshape(
        len(terms), -1
    )
    js = ((z[1 : 1 + x.size] - z[0]) / h[:, None]).T
    points = []
    for k, f in enumerate(partners):
        e = f.effects[0]
        jac = np.column_stack([js, (z[1 + x.size + k] - z[0]) / hp[k]])
        _, grad, hess = _cost_grad_hess(z[0], jac)
        hess = hess + 1e-6 * np.diag(np.maximum(np.diag(hess), 1e-12))
        try:
            step = -np.linalg.solve(hess, grad)
        except np.linalg.LinAlgError:
            step = np.zeros(x.size + 1)
        lo_k, hi_k = np.append(lo, e.bounds[0]), np.append(hi, e.bounds[1])
        x_k = np.append(x, starts[k])
        points.append([np.clip(x_k + a * step, lo_k, hi_k) for a in lengths])
    terms = [
        apply_effects(base, effs + [f.effects[0]], p)
        for f, pts in zip(partners, points)
        for p in pts
    ]
    loss = replay.window_loss(replay.measured[w][None] - replay.predict(terms, w)).mean(axis=1)
    loss = loss.reshape(len(partners), len(lengths))
    best = np.argmin(loss, axis=1)
    return (
        [points[k][best[k]] for k in range(len(partners))],
        [float(loss[k, best[k]]) for k in range(len(partners))],
    )


def _blocks(replay: Replay, block_s: float, folds: int):
    offs = np.concatenate(
        [[0], np.cumsum([int(math.ceil(r.duration / block_s)) + 1 for r in replay.records])]
    )
    rec_t0 = np.array([r.t[0] for r in replay.records])
    local = replay.win_t - rec_t0[replay.win_record]
    blocks = np.floor(local / block_s).astype(int) + offs[replay.win_record]
    return blocks, blocks % folds


def _compare(ref_loss, new_loss, blocks, mask, weight=None):
    """(improvement, t, share of blocks better) of new vs ref on the masked held-out windows;
    with `weight` (per window), also (t_weighted, effective blocks).

    improvement = 1 - sum(new) / sum(ref); t = paired t over blocks of log(ref_b / new_b), the
    per-block log loss ratio (a real effect shrinks the loss by a similar FACTOR in every block,
    while the absolute differences are dominated by the most excited blocks).

    t_weighted: the same log ratios, each block weighted by how much the effect changes the
    predictions there (``weight``: the squared whitened change, summed over the block). An effect
    that only shows at speed (the wheel radius) leaves the quiet blocks' ratios at noise; counting
    them equally drowns its evidence, while a block where the effect changes nothing holds no
    evidence for or against it. The effective number of blocks, (sum w)^2 / sum w^2, sets the
    standard error; the selection requires at least ``min_weighted_blocks`` of them."""
    bl = blocks[mask]
    ub, inv = np.unique(bl, return_inverse=True)
    new = np.zeros(ub.size)
    ref = np.zeros(ub.size)
    np.add.at(new, inv, new_loss[mask])
    np.add.at(ref, inv, ref_loss[mask])
    tot = ref.sum()
    imp = float(1.0 - new.sum() / tot) if tot > 0 else 0.0
    d = np.log(np.maximum(ref, 1e-300) / np.maximum(new, 1e-300))
    t = _t_stat(d, np.ones_like(d))[0]
    if weight is None:
        return imp, t, float(np.mean(d > 0))
    w = np.zeros(ub.size)
    np.add.at(w, inv, weight[mask])
    return imp, t, float(np.mean(d > 0)), *_t_stat(d, w)


def _t_stat(d, w):
    """Weighted paired t of the values d (weights w) and its effective sample size."""
    sw = w.sum()
    if sw <= 0 or d.size < 2:
        return (math.inf if d.sum() > 0 else 0.0), 0.0
    n_eff = sw**2 / float(np.sum(w**2))
    m = float(np.sum(w * d) / sw)
    var = float(np.sum(w * (d - m) ** 2) / sw) * n_eff / max(n_eff - 1.0, 1e-9)
    if var <= 0:
        return (math.inf if m > 0 else 0.0), n_eff
    return m / math.sqrt(var / n_eff), n_eff


def fit_candidates(
    replay: Replay,
    base: ModelTerms,
    candidate_sets,
    cfg: NamingConfig,
    folds,
    blocks,
    x0s,
    ref_losses,
    ref_terms: ModelTerms | None = None,
) -> list:
    """Full-data fit (value, uncertainty) and K-fold held-out losses of several candidate sets,
    all fitted together (batched Levenberg-Marquardt). `ref_terms` is the model the reference
    losses belong to (default `base`): the evidence weights are the candidates' changes to its
    predictions."""
    t0 = time.perf_counter()
    active = replay.active
    wsets = [np.flatnonzero(active)] + [
        np.flatnonzero(active & (folds != f)) for f in range(cfg.folds)
    ]
    # stage 1: the full-data fit of every candidate; stage 2: the fold fits, each started from its
    # candidate's full-data optimum (started from the common guess, a fold of a multi-effect fit
    # can settle in another basin of a trade-off such as torque constant vs friction)
    full_jobs = []
    for effs, x0 in zip(candidate_sets, x0s):
        lo = np.array([e.bounds[0] for e in effs], float)
        hi = np.array([e.bounds[1] for e in effs], float)
        x = _interior(x0, lo, hi)
        full_jobs.append(_Job(list(effs), 0, x, lo, hi, _fd_steps(effs, x, lo, hi)))
    _batched_fit(replay, base, full_jobs, wsets, max_iter=cfg.max_nfev)
    jobs = []
    for fj in full_jobs:
        jobs.append(fj)
        x = _interior(fj.x, fj.lo, fj.hi, margin=1e-4)
        for ws in range(1, cfg.folds + 1):
            jobs.append(
                _Job(
                    fj.effects, ws, x.copy(), fj.lo, fj.hi, _fd_steps(fj.effects, x, fj.lo, fj.hi)
                )
            )
    _batched_fit(replay, base, [j for j in jobs if j.wset > 0], wsets, max_iter=cfg.max_nfev)
    n = cfg.folds + 1
    # held-out: each window predicted by the fit of the fold that did not see it
    idx = wsets[0]
    terms = []
    for c in range(len(candidate_sets)):
        for f in range(cfg.folds):
            j = jobs[c * n + 1 + f]
            terms.append(apply_effects(base, j.effects, j.x))
    pred = replay.predict(terms, idx)
    loss = replay.window_loss(replay.measured[idx][None] - pred).reshape(
        len(candidate_sets), cfg.folds, -1
    )
    # evidence weights: how much each full-data fit changes the reference's predictions
    ref = base if ref_terms is None else ref_terms
    pw = replay.predict(
        [ref]
        + [
            apply_effects(base, jobs[c * n].effects, jobs[c * n].x)
            for c in range(len(candidate_sets))
        ],
        idx,
    )
    change = np.sum(((pw[1:] - pw[:1]) / replay.scales) ** 2, axis=(2, 3))
    e_per = replay.measured.shape[1] * replay.measured.shape[2]
    clusters = (
        np.floor(replay.win_t[idx] / cfg.cluster_s).astype(int) + 100000 * replay.win_record[idx]
    )
    fits = []
    for c, effs in enumerate(candidate_sets):
        full = jobs[c * n]
        held = np.full(len(replay), np.nan)
        held[idx] = loss[c, folds[idx], np.arange(idx.size)]
        cov = _cluster_cov(full.jac, full.res, clusters, e_per)
        fold_x = np.array([jobs[c * n + 1 + f].x for f in range(cfg.folds)])
        unc = _uncertainty(cov, fold_x)
        span = full.hi - full.lo
        start = np.array([start_value(e, base) for e in effs])
        near_lo = (full.x - full.lo < 1e-3 * span) & (np.abs(full.lo - start) > 1e-12)
        near_hi = (full.hi - full.x < 1e-3 * span) & (np.abs(full.hi - start) > 1e-12)
        fit = Fit(
            list(effs),
            full.x.copy(),
            unc,
            full.cost / max(full.res.size, 1),
            held,
            np.array([jobs[c * n + 1 + f].x for f in range(cfg.folds)]),
            at_bound=bool(np.any(near_lo | near_hi)),
            nfev=sum(jobs[c * n + k].nfev for k in range(n)),
        )
        weight = np.zeros(len(replay))
        weight[idx] = change[c]
        (fit.improvement, fit.t, fit.blocks_better, fit.t_weighted, fit.weighted_blocks) = (
            _compare(ref_losses[c], held, blocks, active, weight)
        )
        fits.append(fit)
    dt = time.perf_counter() - t0
    for f in fits:
        f.seconds = dt / len(fits)
    return fits


def _uncertainty(cov, fold_x):
    """One standard deviation per parameter: the larger of the cluster-robust sandwich and the
    delete-a-fold jackknife, (K-1)/K sum_f (x_f - mean)^2. The sandwich sees only the noise the
    clusters carry; the jackknife also sees how the value moves between halves of the record
    (model differences that are not noise, a value that drifts with the excitation) but has only
    K-1 degrees of freedom, so neither alone is trusted."""
    sand = np.clip(np.diag(cov), 0, None)
    k = fold_x.shape[0]
    jack = (k - 1) / k * np.sum((fold_x - fold_x.mean(axis=0)) ** 2, axis=0) if k > 1 else 0 * sand
    return np.sqrt(np.maximum(np.nan_to_num(sand, nan=np.inf), jack))


def _accept(fit: Fit, cfg: NamingConfig) -> bool:
    """The selection rule: the effect removes at least ``min_improvement`` of the held-out loss,
    and the per-block evidence is significant, either counting every block alike (t) or weighting
    the blocks by the effect's visibility (t_weighted over at least ``min_weighted_blocks``
    effective blocks; see ``_compare``)."""
    if fit.improvement < cfg.min_improvement:
        return False
    return fit.t >= cfg.min_t or (
        fit.t_weighted >= cfg.min_t and fit.weighted_blocks >= cfg.min_weighted_blocks
    )


def name_effects(
    replay: Replay,
    base: ModelTerms | None = None,
    candidates=None,
    config: NamingConfig | None = None,
    progress=None,
    scales=None,
) -> NamingResult:
    """Run steps 1-6 of the module docstring on the replay's active windows. `scales` (E, 4):
    whiten with these (a baseline's own error scales) instead of the base model's errors here."""
    cfg = config or NamingConfig()
    base = base if base is not None else replay.model.terms()
    cands = library() if candidates is None else list(candidates)
    timing = {}
    t0 = time.perf_counter()
    if not np.any(replay.active):
        raise ValueError(
            'no windows to fit: the data have no standing/balancing phase '
            f'(phases found: {sorted(set(replay.win_phase))})'
        )
    r0 = replay.residuals([base])[0]
    if scales is None:
        replay.set_scales(r0)
    else:
        replay.scales = np.asarray(scales, float).reshape(replay.measured.shape[1:])
    blocks, folds = _blocks(replay, cfg.block_s, cfg.folds)
    if len(np.unique(folds[replay.active])) < cfg.folds:
        raise ValueError(f'too little data for {cfg.folds} folds of {cfg.block_s} s blocks')
    nominal = np.full(len(replay), np.nan)
    nominal[replay.active] = replay.window_loss(r0[None])[0][replay.active]
    timing['nominal_s'] = time.perf_counter() - t0
    t1 = time.perf_counter()
    x0 = _scan(replay, base, cands, replay.active)
    timing['scan_s'] = time.perf_counter() - t1
    t1 = time.perf_counter()
    singles = fit_candidates(
        replay,
        base,
        [[e] for e in cands],
        cfg,
        folds,
        blocks,
        [[v] for v in x0],
        [nominal] * len(cands),
    )
    if progress:
        for f in singles:
            progress(f)
    timing['singles_s'] = time.perf_counter() - t1
    singles.sort(key=lambda f: -f.improvement)
    selected = None
    combos = []
    t2 = time.perf_counter()
    ok = [f for f in singles if _accept(f, cfg)]
    if ok:
        selected = ok[0]
        while len(selected.effects) < cfg.max_effects:
            used = {e.key for e in selected.effects}
            rest = [f for f in singles if f.effects[0].key not in used]
            if not rest:
                break
            # partners: rank the remaining effects by a conditional scan on top of the accepted set
            # (ranking by their single improvement would try the near-duplicates of the accepted
            # effect first: slope, IMU bias, payload and encoder offset all shift the balance)
            cond = extended_terms(base, selected)
            # each partner's grid also holds its single-fit value: a small effect (an IMU bias of
            # 0.01 rad between grid points 0.075 apart) otherwise scans as no better than nothing
            # and is never tried, while a near-duplicate whose grid happens to fit is
            starts, losses = _scan(
                replay,
                cond,
                [f.effects[0] for f in rest],
                replay.active,
                with_loss=True,
                extra=[f.values for f in rest],
            )
            x0s = [list(selected.values) + [v] for v in starts]
            # the scan holds the accepted values fixed; one joint Gauss-Newton step also lets them
            # move (an IMU bias lets a radius that absorbed the sitting offset return)
            steps, step_losses = _joint_step(replay, base, selected, rest, replay.active)
            for i, (xs, ls) in enumerate(zip(steps, step_losses)):
                if ls < losses[i]:
                    losses[i], x0s[i] = ls, list(xs)
            order = np.argsort(losses)[: cfg.combo_candidates]
            partners = [rest[i] for i in order]
            sets = [selected.effects + p.effects for p in partners]
            x0s = [x0s[i] for i in order]
            fits = fit_candidates(
                replay,
                base,
                sets,
                cfg,
                folds,
                blocks,
                x0s,
                [selected.heldout_loss] * len(sets),
                ref_terms=cond,
            )
            best = None
            for fit in fits:
                fit.reference = selected.key
                fit.improvement_vs_nominal = _compare(
                    nominal, fit.heldout_loss, blocks, replay.active
                )[0]
                combos.append(fit)
                if progress:
                    progress(fit)
                if _accept(fit, cfg) and (best is None or fit.improvement > best.improvement):
                    best = fit
            if best is None:
                best = _admit_by_sitting(replay, base, selected, fits, cfg, blocks)
            if best is None:
                break
            selected = best
            reduced = _drop_redundant(replay, base, selected, cfg, folds, blocks, nominal)
            if reduced is not None:  # the newcomer made an earlier effect moot
                combos.append(reduced)
                selected = reduced
                break
    timing['combos_s'] = time.perf_counter() - t2
    timing['total_s'] = time.perf_counter() - t0
    return NamingResult(
        selected, singles, combos, nominal, replay.scales, cfg, folds, blocks, timing
    )


def _admit_by_sitting(replay, base, selected: Fit, fits, cfg, blocks):
    """The sitting route of the selection rule, for a partner none of which passed the block
    rule: the pitch on the caster is a static, model-free measurement, weighed against its own
    run-to-run noise rather than as the one or two time blocks the sitting lasts. When the
    accepted set misses it by more than ``SITTING_TOL`` (3x the hardware's run-to-run spread),
    the partner is admitted if its set brings it within ``SITTING_TOL``, removes at least
    ``min_improvement`` of the held-out loss (the sitting block predicted by the fold fit that
    did not see it) and leaves the held-out loss off the caster no worse. Best improvement wins;
    None if no partner qualifies."""
    ref = sitting_offset(replay, extended_terms(base, selected))
    if not ref.get('off'):
        return None
    off_caster = replay.active & (replay.win_phase != 'sitting')
    best = None
    for fit in fits:
        if fit.improvement < cfg.min_improvement:
            continue
        if abs(sitting_offset(replay, extended_terms(base, fit))['pooled']) > SITTING_TOL:
            continue
        if _compare(selected.heldout_loss, fit.heldout_loss, blocks, off_caster)[0] < 0.0:
            continue
        if best is None or fit.improvement > best.improvement:
            best = fit
    if best is not None:
        best.reference = f'{selected.key} (sitting route)'
    return best


def _drop_redundant(replay, base, selected: Fit, cfg, folds, blocks, nominal):
    """Backward step after a forward one: refit the set without each earlier effect; if the
    full set does not beat the best such subset by the selection rule, the subset (which still
    holds the newcomer) replaces it. Two near-duplicates (an IMU bias and a waist offset both
    shift the balance) otherwise both stay, one of them at about zero."""
    if len(selected.effects) < 3:
        return None
    subsets, x0s = [], []
    for i in range(len(selected.effects) - 1):
        keep = [k for k in range(len(selected.effects)) if k != i]
        subsets.append([selected.effects[k] for k in keep])
        x0s.append([selected.values[k] for k in keep])
    fits = fit_candidates(replay, base, subsets, cfg, folds, blocks, x0s, [nominal] * len(subsets))
    best = min(fits, key=lambda f: float(np.nansum(f.heldout_loss)))
    imp, t, frac, tw, n_eff = _compare(
        best.heldout_loss, selected.heldout_loss, blocks, replay.active, np.ones(len(replay))
    )
    probe = Fit(
        selected.effects,
        selected.values,
        selected.uncertainty,
        0.0,
        selected.heldout_loss,
        selected.fold_values,
        improvement=imp,
        t=t,
        t_weighted=tw,
        weighted_blocks=n_eff,
    )
    if _accept(probe, cfg):
        return None
    best.improvement_vs_nominal = best.improvement
    best.reference = 'nominal (backward step from ' + selected.key + ')'
    return best


def refine_step(fine: Replay, base: ModelTerms, fit: Fit, cfg: NamingConfig) -> dict:
    """Refit the selected effects on `fine`, the same windows replayed with half the integration
    sub-step, from the values found at the full step; `fit` then holds the finer values, and each
    uncertainty the noise-based one and the change combined in quadrature. The replay's
    semi-implicit Euler is first order, so the change from step h to h/2 estimates the
    discretisation error left at h/2. The noise-based uncertainty does not see it: at the 2 ms
    default a 5 % torque-constant change came out 0.2 % low, 6 sigma, on records simulated at
    1 ms (0.03 % at 1 ms). Returns {key: {value_h, value_h2, substep_s}} (reported units)."""
    lo = np.array([e.bounds[0] for e in fit.effects], float)
    hi = np.array([e.bounds[1] for e in fit.effects], float)
    x = _interior(fit.values, lo, hi, margin=1e-4)
    job = _Job(list(fit.effects), 0, x, lo, hi, _fd_steps(fit.effects, x, lo, hi))
    _batched_fit(fine, base, [job], [np.flatnonzero(fine.active)], max_iter=cfg.max_nfev)
    delta = job.x - fit.values
    out = {
        e.key: {
            'value_h': float(e.display(float(v), base)[0]),
            'value_h2': float(e.display(float(w), base)[0]),
            'substep_s': fine.substep,
        }
        for e, v, w in zip(fit.effects, fit.values, job.x)
    }
    fit.values = job.x.copy()
    fit.uncertainty = np.sqrt(fit.uncertainty**2 + delta**2)
    return out


def drop_null_effects(replay: Replay, base: ModelTerms, result: NamingResult, z_min=2.0) -> list:
    """Drop the selected effects whose value lies within ``z_min`` of its uncertainty (after
    ``refine_step``) of the value that leaves the model unchanged: an effect indistinguishable from
    its own absence is not a finding, however much it trims the held-out loss (on a clean record
    with little sensor noise a torque constant of 0.9994 +- 0.001 x nominal removed 11 % of it,
    t 3.3: the replay's remaining discretisation error, not a motor). The rest is refitted (a
    full ``Fit`` with held-out evidence) and replaces the selection, or none is left. Returns
    the keys dropped."""
    fit = result.selected
    if fit is None:
        return []
    zero = np.array([start_value(e, base) for e in fit.effects])
    null = np.abs(fit.values - zero) < z_min * fit.uncertainty
    if not np.any(null):
        return []
    dropped = [e.key for e, n in zip(fit.effects, null) if n]
    keep = [i for i in range(len(fit.effects)) if not null[i]]
    if not keep:
        result.selected = None
        return dropped
    sub = fit_candidates(
        replay,
        base,
        [[fit.effects[i] for i in keep]],
        result.config,
        result.folds,
        result.blocks,
        [[fit.values[i] for i in keep]],
        [result.nominal_heldout],
    )[0]
    sub.improvement_vs_nominal = sub.improvement
    sub.reference = f'nominal ({", ".join(dropped)} dropped: indistinguishable from zero)'
    result.selected = sub
    return dropped


def extended_terms(base: ModelTerms, fit: Fit | None) -> ModelTerms:
    return base.copy() if fit is None else apply_effects(base, fit.effects, fit.values)


def gaps(replay: Replay, base: ModelTerms, result: NamingResult) -> dict:
    """Gap figures before (nominal) and after (selected effects, full-data fit) on all active
    windows (``gap_metrics``), plus the held-out robust loss (each window predicted by the fold
    fit that did not see it) before and after."""
    r0 = replay.residuals([base])[0]
    before = gap_metrics(replay, r0)
    if result.selected is None:
        after = dict(before)
        held_after = float(np.nanmean(result.nominal_heldout))
    else:
        r1 = replay.residuals([extended_terms(base, result.selected)])[0]
        after = gap_metrics(replay, r1)
        held_after = float(np.nanmean(result.selected.heldout_loss))
    return {
        'before': before,
        'after': after,
        'heldout_loss_before': float(np.nanmean(result.nominal_heldout)),
        'heldout_loss_after': held_after,
    }


def split_values(
    replay: Replay, base: ModelTerms, fit: Fit, cfg: NamingConfig, groups, names
) -> dict:
    """The selected effects' consistency over groups of windows (``groups``: a label per window,
    -1 = unused; ``names``: one per label), by JOINT fits over all groups at once: for each
    selected effect, one fit in which that effect has a value per group and the other selected
    effects one value shared by all groups. Per effect: the group values and their cluster-robust
    uncertainties from that joint fit, chi^2 of the values about their generalised-least-squares
    mean (with the joint covariance, which carries the values' correlation through the shared
    parameters) over the degrees of freedom, and their spread relative to the effect's size. One
    physical effect has one value: groups that disagree far beyond their uncertainty (chi2/dof >
    4) by a spread of more than 10 % of the effect are the sign of an effect absorbing something
    else (between records) or of an effect that changes in time (between the thirds of a
    record). Refitting every effect per group instead lets each group's other values absorb
    whatever differs, and charges an effect with a difference that belongs to another."""
    labels = [
        g for g in range(len(names)) if np.count_nonzero(replay.active & (groups == g)) >= 20
    ]
    if len(labels) < 2 or fit is None:
        return {}
    wsets = [np.flatnonzero(replay.active & (groups == g)) for g in labels]
    effs, n_g = list(fit.effects), len(labels)
    jobs = []
    for i, e in enumerate(effs):
        shared = [k for k in range(len(effs)) if k != i]
        per = [effs[k] for k in shared] + [e] * n_g
        lo = np.array([q.bounds[0] for q in per], float)
        hi = np.array([q.bounds[1] for q in per], float)
        x = _interior(np.append(fit.values[shared], np.repeat(fit.values[i], n_g)), lo, hi, 1e-4)
        job = _Job(per, -1, x, lo, hi, _fd_steps(per, x, lo, hi))
        job.own, job.shared = i, shared
        jobs.append(job)
    _batched_fit(
        replay,
        base,
        jobs,
        wsets,
        max_iter=cfg.max_nfev,
        evaluate=lambda rp, b, js, ws, need_jac=True: _evaluate_joint(rp, b, js, ws, effs),
    )
    e_per = replay.measured.shape[1] * replay.measured.shape[2]
    idx = np.concatenate(wsets)
    clusters = (
        np.floor(replay.win_t[idx] / cfg.cluster_s).astype(int) + 100000 * replay.win_record[idx]
    )
    out = {'groups': [names[g] for g in labels], 'effects': {}, 'method': 'joint'}
    for job, e in zip(jobs, effs):
        cov = _cluster_cov(job.jac, job.res, clusters, e_per)
        ns = len(job.shared)
        vals = job.x[ns:]
        c = np.nan_to_num(cov[ns:, ns:], nan=np.inf)
        sds = np.sqrt(np.clip(np.diag(c), 0, None))
        try:
            cinv = np.linalg.inv(c)
            one = np.ones(n_g)
            mean = float(one @ cinv @ vals / (one @ cinv @ one))
            chi2 = float((vals - mean) @ cinv @ (vals - mean)) / (n_g - 1)
        except np.linalg.LinAlgError:
            mean, chi2 = float(np.mean(vals)), math.nan
        size = abs(float(fit.values[job.own]) - start_value(e, base))
        rel = float(np.std(vals)) / max(size, 1e-12)
        scale = e.display_scale(base)
        out['effects'][e.key] = {
            'values': [float(e.display(float(v), base)[0]) for v in vals],
            'uncertainties': [float(sd * scale) for sd in sds],
            'mean': float(e.display(mean, base)[0]),
            'shared': {
                effs[k].key: float(effs[k].display(float(v), base)[0])
                for k, v in zip(job.shared, job.x[:ns])
            },
            'unit': e.unit,
            'chi2_per_dof': chi2,
            'relative_spread': rel,
            'inconsistent': bool(chi2 > 4.0 and rel > 0.10),
        }
    return out


def _evaluate_joint(replay, base, jobs, wsets, effects):
    """``_evaluate`` for the joint fits of ``split_values``: parameters [shared..., one per group
    of the job's own effect]; per group one batched prediction of every job's trial point and its
    finite-difference points (the shared ones and the group's own), a block-sparse Jacobian."""
    res = {id(j): [] for j in jobs}
    rows = {id(j): [] for j in jobs}
    n_res = 0
    for g, w in enumerate(wsets):
        terms, owner = [], []
        for j in jobs:
            ns = len(j.shared)
            cols = list(range(ns)) + [ns + g]
            pts = [j.trial] + [j.trial + np.eye(j.trial.size)[c] * j.h[c] for c in cols]
            for x in pts:
                v = np.empty(len(effects))
                v[j.shared], v[j.own] = x[:ns], x[ns + g]
                terms.append(apply_effects(base, effects, v))
            owner.append(cols)
        pred = replay.predict(terms, w)
        z = ((replay.measured[w][None] - pred) / replay.scales).reshape(len(terms), -1)
        k = 0
        for j, cols in zip(jobs, owner):
            res[id(j)].append(z[k])
            d = (z[k + 1 : k + 1 + len(cols)] - z[k]) / j.h[cols][:, None]
            rows[id(j)].append((n_res, cols, d.T))
            j.nfev += 1 + len(cols)
            k += 1 + len(cols)
        n_res += z.shape[1]
    for j in jobs:
        j.trial_res = np.concatenate(res[id(j)])
        jac = np.zeros((n_res, j.trial.size))
        for start, cols, block in rows[id(j)]:
            jac[start : start + block.shape[0], cols] = block
        j.trial_jac = jac


def per_record_values(replay: Replay, base: ModelTerms, fit: Fit, cfg: NamingConfig) -> dict:
    """``split_values`` over the records."""
    return split_values(
        replay, base, fit, cfg, replay.win_record, [r.name for r in replay.records]
    )


def per_third_values(replay: Replay, base: ModelTerms, fit: Fit, cfg: NamingConfig) -> dict:
    """``split_values`` over the first, middle and last third of every record (pooled)."""
    third = np.zeros(len(replay), int)
    for ri, rec in enumerate(replay.records):
        m = replay.win_record == ri
        third[m] = np.minimum(
            (3 * (replay.win_t[m] - rec.t[0]) / max(rec.duration, 1e-9)).astype(int), 2
        )
    return split_values(
        replay, base, fit, cfg, third, ['first third', 'middle third', 'last third']
    )
