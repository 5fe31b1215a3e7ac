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
   ``compare``) is >= ``min_t`` over at least ``min_weighted_blocks`` effective blocks. Forward up
   to ``max_effects`` (partners ranked by the better of a conditional scan, whose grids hold each
   effect's zero and its single-fit value, and a joint Gauss-Newton step that lets the accepted
   values move with the partner, ``joint_step``),
   with a backward step once a third effect enters (``_drop_redundant``). With a long record an
   information criterion alone admits spurious terms; the minimum effect size on held-out data
   does not. When no partner passes and the accepted set misses the
   pitch on the caster, the sitting route (``_admit_by_sitting``) weighs that static evidence
   against its own run-to-run noise instead of as the block or two the sitting lasts.
6. Uncertainty: the larger of the cluster-robust sandwich (``cluster_s`` clusters) and the
   delete-a-fold jackknife of the fold fits (``fitting.fit_candidates``), combined with the
   discretisation error of the replay (``refine_step``, run by ``krang_discrepancy.report``).
7. Consistency: ``per_record_values`` / ``per_third_values`` refit the selection per record and
   per third of the records (``split_values``).

The fits are ``krang_discrepancy.fitting``'s, the held-out comparisons
``krang_discrepancy.evidence``'s and the consistency checks ``krang_discrepancy.consistency``'s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from krang_model.effects import ModelTerms, library

from .evidence import compare, time_blocks
from .fitting import Fit, extended_terms, fit_candidates, joint_step, scan, start_value
from .replay import Replay, gap_metrics
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


def _accept(fit: Fit, cfg: NamingConfig) -> bool:
    """The selection rule: the effect removes at least ``min_improvement`` of the held-out loss,
    and the per-block evidence is significant, either counting every block alike (t) or weighting
    the blocks by the effect's visibility (t_weighted over at least ``min_weighted_blocks``
    effective blocks; see ``compare``)."""
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
    blocks, folds = time_blocks(replay, cfg.block_s, cfg.folds)
    if len(np.unique(folds[replay.active])) < cfg.folds:
        raise ValueError(f'too little data for {cfg.folds} folds of {cfg.block_s} s blocks')
    nominal = np.full(len(replay), np.nan)
    nominal[replay.active] = replay.window_loss(r0[None])[0][replay.active]
    timing['nominal_s'] = time.perf_counter() - t0
    t1 = time.perf_counter()
    x0 = scan(replay, base, cands, replay.active)
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
            starts, losses = scan(
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
            steps, step_losses = joint_step(replay, base, selected, rest, replay.active)
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
                fit.improvement_vs_nominal = compare(
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
        if compare(selected.heldout_loss, fit.heldout_loss, blocks, off_caster)[0] < 0.0:
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
    imp, t, frac, tw, n_eff = compare(
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


def drop_null_effects(replay: Replay, base: ModelTerms, result: NamingResult, z_min=2.0) -> list:
    """Drop the selected effects whose value lies within ``z_min`` of its uncertainty (after
    ``refine_step``) of the value that leaves the model unchanged: an effect indistinguishable from
    its own absence is not a finding, however much it trims the held-out loss (on a clean record
    with little sensor noise a torque constant of 0.9994 +- 0.001 x nominal removed 11 % of it,
    t 3.3: the replay's remaining discretisation error, not a motor). The rest is refitted
    (``drop_effects``). Returns the keys dropped."""
    fit = result.selected
    if fit is None:
        return []
    zero = np.array([start_value(e, base) for e in fit.effects])
    null = np.abs(fit.values - zero) < z_min * fit.uncertainty
    dropped = [e.key for e, n in zip(fit.effects, null) if n]
    drop_effects(replay, base, result, dropped, 'indistinguishable from zero')
    return dropped


def drop_effects(replay: Replay, base: ModelTerms, result: NamingResult, keys, why: str) -> None:
    """Remove the selected effects `keys` and refit the rest (a full ``Fit`` with held-out
    evidence against the nominal model), which replaces the selection; none is left when every
    effect goes."""
    fit = result.selected
    if fit is None or not keys:
        return
    keep = [i for i, e in enumerate(fit.effects) if e.key not in keys]
    if not keep:
        result.selected = None
        return
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
    sub.reference = f'nominal ({", ".join(keys)} dropped: {why})'
    result.selected = sub


def changing_partners(result: NamingResult, drift: dict) -> list:
    """The partners (every selected effect but the first, the best single) whose values change
    between the thirds of the records (``consistency.per_third_values``), when the first does
    not: a partner admitted on top of the effect that explains the data can absorb something
    that differs over a record (the excitation, the pose) and drift, which says nothing about
    that effect (``krang_discrepancy.report`` drops them when no other rule of the verdict
    fires). A first effect that drifts is the finding itself (``verdict.decide``)."""
    fit = result.selected
    effects = (drift or {}).get('effects', {})
    if (
        fit is None
        or len(fit.effects) < 2
        or effects.get(fit.effects[0].key, {}).get('inconsistent')
    ):
        return []
    return [e.key for e in fit.effects[1:] if effects.get(e.key, {}).get('inconsistent')]


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
