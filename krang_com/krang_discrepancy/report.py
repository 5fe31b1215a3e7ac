"""The whole workflow, ``run_discrepancy(measured, out_dir)``, and its outputs: DIR/report.md,
DIR/*.png, DIR/extended_model.yaml, DIR/result.json.

  1. load and align the records (``krang_discrepancy.loaders``), build the multiple-shooting
     replay (``replay``);
  2. locate the disagreement under the nominal model (``locate``);
  3. name the missing effect(s) by held-out improvement (``naming``);
  4. write the extended model (``extended_model``), read it back and re-simulate every window
     with it: the gap after is computed from the file, not from the fit in memory;
  5. replay every run whose controller is known in closed loop with the model before and after
     (``closed_loop_check``): does the model's robot stand up as the real one did?
  6. judge what is left (``verdict``), write the report (``markdown``) and the figures
     (``figures``), and return the ``krang discrepancy --json`` object (``contract``).

The gap (JSON ``gap_before`` / ``gap_after``) is the RMS prediction error over the fitting windows
(standing up, balancing, moving joints, sitting down), the three comparison points of the horizon
and the four signals (pitch, pitch rate, wheel angle, wheel rate), each signal whitened by the
nominal model's robust RMS error for it: about 1 before, the share left after. The physical
figures (RMS pitch and wheel-angle error at the horizon, rad) come as ``gap_pitch_rad`` and
``gap_wheel_rad`` [before, after]; the report adds the rest.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from krang_model.effects import apply_effects, library
from krang_model.files import atomic_open

from .closed_loop_check import (
    ClosedLoopRuns,
    closed_loop_check,
    closed_loop_json,
    default_workers,
)
from .consistency import per_record_values, per_third_values
from .contract import contract, with_verdict
from .extended_model import load_extended_model, plain, write_extended_model
from .figures import plot_closed_loop, plot_evidence, plot_gap, plot_gap_bars
from .fitting import extended_terms, refine_step
from .loaders import load_measured
from .locate import locate, plot_location
from .markdown import write_report
from .naming import (
    NamingConfig,
    changing_partners,
    drop_effects,
    drop_null_effects,
    name_effects,
)
from .nominal import NominalModel
from .phases import PHASES
from .record import resample
from .replay import Replay, ReplayConfig, gap_metrics
from .verdict import (
    MAX_GAP,
    decide,
    gap_test,
    phase_gaps,
    phase_matched_gap,
    residual_structure,
    rules_fired,
    sitting_offset,
)


def run_discrepancy(
    measured,
    out_dir,
    *,
    model: NominalModel | None = None,
    candidates=None,
    replay_config: ReplayConfig | None = None,
    naming_config: NamingConfig | None = None,
    phases=None,
    plots: bool = True,
    rate_hz=None,
    log=None,
    baseline=None,
    closed_loop: bool = True,
) -> dict:
    """The workflow (module docstring). `measured`: paths (files/folders) or Record objects.
    `baseline`: an extended_model.yaml of earlier runs: the new data are compared with the robot as
    that file corrects it, whitened by its own typical errors there (so the gap says how far off it
    is), and the effects named are what changed. `closed_loop`: also replay every run whose
    controller is known in closed loop, before and after (``closed_loop_check``; its verdict rule
    ``closed_loop_stand_up``).
    Returns {'json': contract, 'result': NamingResult, 'location': Location, 'replay': Replay,
    'timing': {stage: s}, 'files': [...]}."""
    say = log or (lambda msg: None)
    timing = {}
    t = time.perf_counter()
    out_dir = Path(out_dir)
    records = (
        [r for r in measured if not isinstance(r, (str, Path))]
        if isinstance(measured, (list, tuple))
        else []
    )
    paths = (
        [r for r in measured if isinstance(r, (str, Path))]
        if isinstance(measured, (list, tuple))
        else [measured]
    )
    if paths:
        records += load_measured(paths, rate_hz)
    out_dir.mkdir(parents=True, exist_ok=True)  # only once the input is known to be readable
    if rate_hz is None and len({round(r.period, 6) for r in records}) > 1:
        # one clock for all: the slowest record's rate
        period = max(r.period for r in records)
        records = [_resample_record(r, period) for r in records]
    base_doc = None
    if baseline is not None:
        with open(baseline) as f:
            base_doc = yaml.safe_load(f)
        base_doc['path'] = str(baseline)
        model = model or NominalModel.default(base_doc.get('nominal', {}).get('beta') or None)
    model = model or NominalModel.default()
    base = model.terms() if base_doc is None else load_extended_model(baseline, model.terms())
    timing['load_s'] = time.perf_counter() - t
    say(f'loaded {len(records)} record(s), {sum(r.duration for r in records):.1f} s of data')
    # the nominal model's closed-loop replays need nothing the naming finds: they start now,
    # in worker processes beside the fits (``ClosedLoopRuns``)
    workers = (replay_config or ReplayConfig()).workers or default_workers()
    sims = ClosedLoopRuns(records, model, workers=workers) if closed_loop else None
    if sims is not None:
        sims.submit('before', base)
    try:
        return _workflow(
            records,
            model,
            base,
            base_doc,
            baseline,
            out_dir,
            sims,
            timing,
            say,
            replay_config=replay_config,
            phases=phases,
            candidates=candidates,
            naming_config=naming_config,
            plots=plots,
        )
    finally:
        if sims is not None:
            sims.close()


def _workflow(
    records,
    model,
    base,
    base_doc,
    baseline,
    out_dir,
    sims,
    timing,
    say,
    *,
    replay_config,
    phases,
    candidates,
    naming_config,
    plots,
) -> dict:
    """``run_discrepancy`` once the records and the model are known; `sims` the closed-loop
    replays (None: no closed-loop check)."""
    t = time.perf_counter()
    replay = Replay(records, model, replay_config, phases)
    timing['replay_setup_s'] = time.perf_counter() - t
    if replay.widened():
        say(replay.widened())
    t = time.perf_counter()
    loc = locate(replay, base)
    timing['locate_s'] = time.perf_counter() - t
    say('located: ' + '; '.join(loc.summary))
    t = time.perf_counter()
    cands = library() if candidates is None else library(candidates)
    ref_scales = _reference_scales(base_doc, replay, say)
    ref_phase_gaps = (base_doc or {}).get('reference', {}).get('phase_gaps') or {}
    result = name_effects(
        replay,
        base,
        cands,
        naming_config,
        scales=ref_scales,
        progress=lambda f: say(
            f'  {f.key}: held-out improvement {f.improvement:+.3f}, t {f.t:.1f}'
        ),
    )
    timing['naming_s'] = time.perf_counter() - t
    say(f'named: {result.name}')
    discretisation = {}
    if result.selected is not None:
        t = time.perf_counter()
        fine = Replay(records, model, replace(replay.cfg, substep_s=replay.substep / 2), phases)
        fine.scales = replay.scales
        discretisation = refine_step(fine, base, result.selected, result.config)
        dropped = drop_null_effects(replay, base, result)
        if dropped:
            say(f'dropped (within 2 sigma of zero): {", ".join(dropped)}; named: {result.name}')
            discretisation = {k: v for k, v in discretisation.items() if k not in dropped}
        timing['refine_s'] = time.perf_counter() - t
    t = time.perf_counter()
    drift = per_third_values(replay, base, result.selected, result.config)
    structure = residual_structure(
        replay, extended_terms(base, result.selected), result.folds, result.blocks
    )
    changing = {}
    moving = changing_partners(result, drift)
    # a partner that changes in time is dropped when its drift is the only reason left for
    # 'unexplained': the rest is refitted and judged by every rule. When another rule fires
    # anyway, the partial correction keeps it (the best the library can do).
    matched = ref_phase_gaps if ref_scales is not None else None
    while moving and not _other_rules_fire(replay, base, result, structure, matched):
        changing.update({k: drift['effects'][k] for k in moving})
        drop_effects(replay, base, result, moving, 'changes over the thirds of the records')
        say(f'dropped (changes in time): {", ".join(moving)}; named: {result.name}')
        discretisation = {k: v for k, v in discretisation.items() if k not in moving}
        discretisation.update(refine_step(fine, base, result.selected, result.config))
        drift = per_third_values(replay, base, result.selected, result.config)
        structure = residual_structure(
            replay, extended_terms(base, result.selected), result.folds, result.blocks
        )
        moving = changing_partners(result, drift)
    timing['structure_s'] = time.perf_counter() - t
    ypath = out_dir / 'extended_model.yaml'
    sources = [r.source or r.name for r in records]
    write_extended_model(
        ypath, result.selected, model, sources=sources, base=base, baseline=base_doc
    )
    ext_terms = load_extended_model(ypath, model.terms())
    if sims is not None:  # the extended model's closed-loop replays run beside the rest
        sims.submit('after', ext_terms)
    t = time.perf_counter()
    per_record = per_record_values(replay, base, result.selected, result.config)
    timing['per_record_s'] = time.perf_counter() - t
    split = [k for k, v in per_record.get('effects', {}).items() if v['inconsistent']]
    if split:
        say(f'per-record values disagree beyond their uncertainty: {", ".join(split)}')
    t = time.perf_counter()
    r0 = replay.residuals([base])[0]
    r1 = replay.residuals([ext_terms])[0]
    gaps_yaml = {'before': gap_metrics(replay, r0), 'after': gap_metrics(replay, r1)}
    if ref_scales is not None:
        for key, r in (('before', r0), ('after', r1)):
            gaps_yaml[key]['gap_matched'] = phase_matched_gap(replay, r, ref_phase_gaps)
    steps = []
    if result.selected is not None:
        for k in range(1, len(result.selected.effects) + 1):
            tk = apply_effects(base, result.selected.effects[:k], result.selected.values[:k])
            steps.append(gap_metrics(replay, replay.residuals([tk])[0])['gap'])
    gaps_yaml['steps'] = steps
    per_phase = {}
    for ph in PHASES:
        w = replay.win_phase == ph
        if np.any(w):
            per_phase[ph] = {
                'before': gap_metrics(replay, r0, w),
                'after': gap_metrics(replay, r1, w),
            }
    heldout = {
        'before': float(np.nanmean(result.nominal_heldout)),
        'after': float(np.nanmean(result.selected.heldout_loss))
        if result.selected
        else float(np.nanmean(result.nominal_heldout)),
    }
    sitting = sitting_offset(replay, extended_terms(base, result.selected))
    excess = gap_test(replay, r1)
    closed = None
    if sims is not None:
        t_cl = time.perf_counter()
        closed = closed_loop_check(records, model, base, ext_terms, runs=sims)
        timing['closed_loop_s'] = time.perf_counter() - t_cl
        if closed['runs']:
            say(
                f'closed loop: lift-off gap {closed["lift_off_gap_s"][0]:.3g} -> '
                f'{closed["lift_off_gap_s"][1]:.3g} s'
            )
        else:
            closed = None
    verdict, reason = decide(
        result, structure, gaps_yaml, ref_scales is not None, drift, sitting, excess, closed
    )
    fired = rules_fired(
        result, structure, gaps_yaml, ref_scales is not None, drift, sitting, excess, closed
    )
    say(f'verdict: {verdict}' + (f' ({reason})' if reason else ''))
    r1a = r1[replay.active]
    own = np.sqrt(np.median(r1a**2, axis=0) / 0.4549) + 1e-12
    extra = {
        'verdict': verdict,
        'verdict_reason': reason,
        'rules_fired': fired,
        'signature': structure.as_dict(),
        'per_record': per_record,
        'per_third': drift,
        'sitting_offset': sitting,
        'gap_test': excess,
        'reference': {
            'scales': own.tolist(),
            'phase_gaps': phase_gaps(replay, r1, own),
            'horizon_s': replay.horizon,
            'n_eval': int(replay.measured.shape[1]),
            'meaning': 'robust RMS error of this model on its own data, per '
            'horizon point and signal: the yardstick of later runs; phase_gaps: its gap in '
            'those scales in each phase, which later runs are matched to',
        },
    }
    # rewrite the YAML with the gap figures
    write_extended_model(
        ypath,
        result.selected,
        model,
        sources=sources,
        base=base,
        baseline=base_doc,
        extra=extra,
        gaps={
            'metric': f'RMS whitened error of {replay.horizon:.3g} s predictions (4 signals)',
            'before': gaps_yaml['before']['gap'],
            'after': gaps_yaml['after']['gap'],
            'pitch_rad': [gaps_yaml['before']['rms_q_base'], gaps_yaml['after']['rms_q_base']],
            'wheel_rad': [gaps_yaml['before']['rms_wheel'], gaps_yaml['after']['rms_wheel']],
        },
    )
    js = contract(result, gaps_yaml, base)
    js = with_verdict(js, verdict, reason, structure, result, base)
    if base_doc is not None:
        js['baseline'] = str(baseline)
    if discretisation:
        js['discretisation'] = discretisation
    js['rules_fired'] = fired
    if changing:
        js['dropped_changing'] = changing
    if sitting:
        js['sitting_offset'] = sitting
    if excess:
        js['gap_test'] = excess
    if closed:
        js['closed_loop'] = closed_loop_json(closed)
    if per_record:
        js['per_record'] = per_record
        if split:
            js['misattribution_warning'] = (
                f'{", ".join(split)}: the records give values that differ far beyond their '
                'uncertainties (chi2/dof > 4, spread > 10 %): one robot has one value, so the '
                'effect is absorbing something else that differs between the runs'
            )
    timing['resimulate_s'] = time.perf_counter() - t - timing.get('closed_loop_s', 0.0)
    files = []
    t = time.perf_counter()
    if plots:
        files += plot_location(loc, replay, out_dir)
        files.append(plot_evidence(result, out_dir))
        counts = np.bincount(replay.win_record[replay.active], minlength=len(records))
        ri = int(np.argmax(counts))
        f = plot_gap(replay, base, ext_terms, out_dir, ri)
        if f:
            files.append(f)
        files.append(plot_gap_bars(per_phase, out_dir))
        if closed:
            files.append(plot_closed_loop(closed, out_dir))
    timing['plots_s'] = time.perf_counter() - t
    t = time.perf_counter()
    write_report(
        out_dir / 'report.md',
        records,
        replay,
        loc,
        result,
        gaps_yaml,
        per_phase,
        heldout,
        js,
        files,
        model,
        timing,
    )
    timing['report_s'] = time.perf_counter() - t
    with atomic_open(out_dir / 'result.json', 'w') as f:
        json.dump(plain(js), f, indent=1)
    return {
        'json': js,
        'result': result,
        'location': loc,
        'replay': replay,
        'timing': timing,
        'structure': structure,
        'verdict': verdict,
        'per_third': drift,
        'files': files,
        'gaps': gaps_yaml,
        'per_phase': per_phase,
        'heldout': heldout,
        'extended_terms': ext_terms,
        'closed_loop': closed,
    }


def _other_rules_fire(replay, base, result, structure, ref_phase_gaps) -> bool:
    """Whether a rule other than the drift over thirds makes the selection `unexplained`
    (``verdict.decide``): the residual's structure, the pitch on the caster, and the gap (the gap
    test on the model's own yardstick; judged against a baseline, `ref_phase_gaps` not None, the
    phase-matched gap)."""
    if structure.significant:
        return True
    terms = extended_terms(base, result.selected)
    if sitting_offset(replay, terms).get('off'):
        return True
    r1 = replay.residuals([terms])[0]
    if ref_phase_gaps is None:
        return bool(gap_test(replay, r1).get('exceeds'))
    return phase_matched_gap(replay, r1, ref_phase_gaps) > MAX_GAP


def _reference_scales(base_doc, replay, say):
    """The baseline's own error scales, if they fit this replay's horizon points."""
    ref = (base_doc or {}).get('reference')
    if not ref:
        if base_doc is not None:
            say(
                'baseline has no reference scales: the gap is in units of its errors on these data'
            )
        return None
    sc = np.asarray(ref['scales'], float)
    # records at another sample rate land on a slightly different horizon; the scales of a
    # horizon within 10 % still measure the same thing
    if (
        sc.shape != replay.measured.shape[1:]
        or abs(ref['horizon_s'] - replay.horizon) > 0.1 * replay.horizon
    ):
        say(
            f'baseline reference scales are for a {ref["horizon_s"]:.3g} s horizon, not '
            f'{replay.horizon:.3g} s: not used (pass --horizon to match)'
        )
        return None
    return sc


def _resample_record(rec, period):
    if abs(rec.period - period) < 1e-9:
        return rec
    grid = np.arange(rec.t[0], rec.t[-1] + 1e-12, period)
    return replace(
        rec,
        t=grid,
        q_base=np.interp(grid, rec.t, rec.q_base),
        pitch_rate=np.interp(grid, rec.t, rec.pitch_rate),
        wheel=np.interp(grid, rec.t, rec.wheel),
        wheel_rate=np.interp(grid, rec.t, rec.wheel_rate),
        joints=resample(rec.t, rec.joints, grid),
    )
