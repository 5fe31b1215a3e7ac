"""Is a named effect a constant of the robot? Its values over groups of windows (the records, or
the thirds of every record) from one joint fit, and their agreement beyond their uncertainty."""

from __future__ import annotations

import math

import numpy as np

from krang_model.effects import ModelTerms, apply_effects

from .fitting import (
    Fit,
    FitJob,
    batched_fit,
    cluster_cov,
    fd_steps,
    interior,
    start_value,
    window_clusters,
)
from .replay import Replay


def split_values(replay: Replay, base: ModelTerms, fit: Fit, cfg, groups, names) -> dict:
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
        x = interior(np.append(fit.values[shared], np.repeat(fit.values[i], n_g)), lo, hi, 1e-4)
        job = FitJob(per, -1, x, lo, hi, fd_steps(per, x, lo, hi))
        job.own, job.shared = i, shared
        jobs.append(job)
    batched_fit(
        replay,
        base,
        jobs,
        wsets,
        max_iter=cfg.max_nfev,
        evaluate=lambda rp, b, js, ws, need_jac=True: _evaluate_joint(
            rp, b, js, ws, effs, need_jac
        ),
    )
    e_per = replay.measured.shape[1] * replay.measured.shape[2]
    idx = np.concatenate(wsets)
    clusters = window_clusters(replay, cfg.cluster_s)[idx]
    out = {'groups': [names[g] for g in labels], 'effects': {}, 'method': 'joint'}
    for job, e in zip(jobs, effs):
        cov = cluster_cov(job.jac, job.res, clusters, e_per)
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


def _evaluate_joint(replay, base, jobs, wsets, effects, need_jac=True):
    """The evaluation of ``fitting.batched_fit`` for the joint fits of ``split_values``:
    parameters [shared..., one per group of the job's own effect]; per group one batched
    prediction of every job's trial point and its finite-difference points (the shared ones and
    the group's own), a block-sparse Jacobian. need_jac as ``fitting._evaluate``."""
    res = {id(j): [] for j in jobs}
    rows = {id(j): [] for j in jobs}
    n_res = 0
    for g, w in enumerate(wsets):
        terms, owner = [], []
        for j in jobs:
            ns = len(j.shared)
            cols = list(range(ns)) + [ns + g] if need_jac else []
            pts = [j.trial + np.eye(j.trial.size)[c] * j.h[c] for c in cols]
            if need_jac != 'columns':
                pts = [j.trial] + pts
            for x in pts:
                v = np.empty(len(effects))
                v[j.shared], v[j.own] = x[:ns], x[ns + g]
                terms.append(apply_effects(base, effects, v))
            owner.append(cols)
        pred = replay.predict(terms, w)
        z = ((replay.measured[w][None] - pred) / replay.scales).reshape(len(terms), -1)
        k = 0
        for j, cols in zip(jobs, owner):
            if need_jac == 'columns':
                r0 = j.trial_res[n_res : n_res + z.shape[1]]
                d = (z[k : k + len(cols)] - r0) / j.h[cols][:, None]
                k += len(cols)
            else:
                r0 = z[k]
                res[id(j)].append(r0)
                d = (z[k + 1 : k + 1 + len(cols)] - r0) / j.h[cols][:, None]
                k += 1 + len(cols)
            if need_jac:
                rows[id(j)].append((n_res, cols, d.T))
            j.nfev += len(cols) + (need_jac != 'columns')
        n_res += z.shape[1]
    for j in jobs:
        if need_jac != 'columns':
            j.trial_res = np.concatenate(res[id(j)])
        if not need_jac:
            j.trial_jac = None
            continue
        jac = np.zeros((n_res, j.trial.size))
        for start, cols, block in rows[id(j)]:
            jac[start : start + block.shape[0], cols] = block
        j.trial_jac = jac


def per_record_values(replay: Replay, base: ModelTerms, fit: Fit, cfg) -> dict:
    """``split_values`` over the records."""
    return split_values(
        replay, base, fit, cfg, replay.win_record, [r.name for r in replay.records]
    )


def per_third_values(replay: Replay, base: ModelTerms, fit: Fit, cfg) -> dict:
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
