"""Held-out evidence: windows grouped in time blocks (and folds), and the paired comparison of two
models' held-out losses over those blocks, the test every rule of the workflow applies (the
selection of an effect, the residual-structure test, the ambiguity of a runner-up)."""

from __future__ import annotations

import math

import numpy as np

from .replay import Replay


def time_blocks(replay: Replay, block_s: float, folds: int):
    offs = np.concatenate(
        [[0], np.cumsum([int(math.ceil(r.duration / block_s)) + 1 for r in replay.records])]
    )
    rec_t0 = np.array([r.t[0] for r in replay.records])
    local = replay.win_t - rec_t0[replay.win_record]
    blocks = np.floor(local / block_s).astype(int) + offs[replay.win_record]
    return blocks, blocks % folds


def compare(ref_loss, new_loss, blocks, mask, weight=None):
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
