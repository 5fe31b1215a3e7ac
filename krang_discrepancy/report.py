"""The whole workflow and its outputs: DIR/report.md, DIR/*.png, DIR/extended_model.yaml.

``run_discrepancy(measured, out_dir)``:
  1. load and align the records (data.py), build the multiple-shooting replay;
  2. locate the disagreement under the nominal model (locate.py);
  3. name the missing effect(s) by held-out improvement (naming.py);
  4. write the extended model (the effects and their values, mapped onto
     ``krang_sim.physics.SimEffects``) to extended_model.yaml, read it back and re-simulate every
     window with it: the gap after is computed from the file, not from the fit in memory;
  5. write the report and the figures, and return the ``krang discrepancy --json`` object.

The gap (JSON ``gap_before`` / ``gap_after``) is the RMS prediction error over the fitting windows
(standing up, balancing, moving joints, sitting down), the three comparison points of the horizon
and the four signals (pitch, pitch rate, wheel angle, wheel rate), each signal whitened by the
nominal model's robust RMS error for it: about 1 before, the share left after. The physical
figures (RMS pitch and wheel-angle error at the horizon, rad) come as ``gap_pitch_rad`` and
``gap_wheel_rad`` [before, after]; the report adds the rest.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from .loaders import load_measured
from .nominal import NominalModel
from .phases import PHASES
from .record import CHANNEL_UNITS, CHANNELS, resample
from .replay import Replay, ReplayConfig, gap_metrics
from krang_model.effects import ModelTerms, apply_effects, get_effect, library
from .locate import PHASE_COLOURS, locate, plot_location, shade_phases
from .naming import (
    NamingConfig,
    drop_null_effects,
    extended_terms,
    name_effects,
    per_record_values,
    per_third_values,
    refine_step,
)
from .verdict import (
    MAX_GAP,
    SITTING_TOL,
    gap_sentence,
    gap_test,
    phase_gaps,
    phase_matched_gap,
    residual_structure,
    sitting_offset,
)
from krang_model.files import atomic_open, save_figure, write_text

FORMAT = 'krang_discrepancy/extended_model/1'


# ----------------------------------------------------------------------------- extended model YAML


def effect_entries(fit, base: ModelTerms) -> list:
    """One dict per effect of a fit: name, key, value (reported units, physical: a torque
    constant in N m/A of the robot with `base`'s Kt times the fitted scale), parameter,
    uncertainty."""
    out = []
    if fit is None:
        return out
    for e, v, u in zip(fit.effects, fit.values, fit.uncertainty):
        dv, unit = e.display(float(v), base)
        out.append(
            {
                'effect': e.name,
                'key': e.key,
                'value': float(dv),
                'unit': unit,
                'uncertainty': float(u) * e.display_scale(base),
                'parameter': float(v),
                **({'detail': e.detail} if e.detail else {}),
            }
        )
    return out


def write_extended_model(
    path, fit, model: NominalModel, *, sources=(), gaps=None, base=None, baseline=None, extra=None
) -> dict:
    """The extended model as YAML: the nominal model it extends, the effects (value, unit,
    uncertainty, fitted parameter) and ``sim_effects``, the keyword arguments of
    ``krang_sim.physics.SimEffects`` that make the simulator carry them.

    With ``baseline`` (the document of an earlier extended model, whose terms are `base`) the file
    is complete: the baseline's effects first (marked with the file they came from), then the new
    ones, so that it can serve as the next baseline (the effects apply in order)."""
    base = model.terms() if base is None else base
    new = effect_entries(fit, base)
    old = [
        dict(e, **({} if 'from' in e else {'from': baseline.get('path', '')}))
        for e in (baseline or {}).get('effects', [])
    ]
    entries = old + new
    sim = {}
    not_simulable = []
    for ent in entries:
        e = get_effect(ent['key'])
        kw = e.sim_effects(ent['parameter'])
        if kw is None:
            not_simulable.append(e.key)
            continue
        for k, v in kw.items():
            if isinstance(v, dict):  # drive_extra: amounts per Drivetrain field add up
                merged = dict(sim.get(k, {}))
                for field_name, amount in v.items():
                    merged[field_name] = merged.get(field_name, 0.0) + amount
                sim[k] = merged
            elif (
                k in sim
                and isinstance(v, (int, float))
                and k not in ('torque_constant_scale', 'wheel_radius_m')
            ):
                sim[k] = sim[k] + v
            elif k == 'torque_constant_scale' and k in sim:
                sim[k] = sim[k] * v
            else:
                sim[k] = v
    doc = {
        'format': FORMAT,
        'nominal': {
            'beta': model.beta_source,
            'wheel_radius_m': float(model.drive.wheel_radius),
            'torque_constant_Nm_per_A': float(model.drive.torque_constant),
            'viscous_friction_Nm_s': float(model.drive.viscous_friction),
            'coulomb_friction_Nm': float(model.drive.coulomb_friction),
            'floor_slope_rad': float(model.drive.floor_slope),
        },
        'effects': [{k: v for k, v in ent.items()} for ent in entries],
        'sim_effects': sim,
        'not_simulable': not_simulable,
        'data': [str(s) for s in sources],
    }
    if baseline:
        doc['baseline'] = baseline.get('path', '')
    if extra:
        doc.update(extra)
    if gaps:
        doc['gap'] = gaps
    with atomic_open(path, 'w') as f:
        f.write(
            '# Extended Krang model found by `krang discrepancy`. `sim_effects` are keyword '
            'arguments\n'
            '# of krang_sim.physics.SimEffects: SimConfig(effects=SimEffects(**sim_effects)).\n'
        )
        yaml.safe_dump(_plain(doc), f, sort_keys=False)
    return doc


def _plain(o):
    if isinstance(o, dict):
        return {str(k): _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    return o


def load_extended_model(path, base: ModelTerms | None = None):
    """(SimEffects, ModelTerms) of an extended-model YAML. ModelTerms applies every listed effect
    (by key, from the registry) at its fitted parameter on top of `base` (default: nominal)."""
    from krang_sim.physics import SimEffects

    with open(path) as f:
        doc = yaml.safe_load(f)
    if not isinstance(doc, dict) or doc.get('format') != FORMAT:
        raise ValueError(f'{path}: not an extended-model file ({FORMAT})')
    sim = dict(doc.get('sim_effects') or {})
    if 'payload_com_m' in sim:
        sim['payload_com_m'] = tuple(sim['payload_com_m'])
    effects = SimEffects(**sim)
    if base is None:
        base = NominalModel.default(doc['nominal'].get('beta') or None).terms()
    effs = [get_effect(e['key']) for e in doc.get('effects', [])]
    terms = apply_effects(base, effs, [e['parameter'] for e in doc.get('effects', [])])
    return effects, terms


# ----------------------------------------------------------------------------- figures


def _plot_evidence(result, out_dir):
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fits = result.singles + result.combos
    fig, ax = plt.subplots(figsize=(9, 0.32 * len(fits) + 1.5))
    y = np.arange(len(fits))[::-1]
    imp = [f.improvement for f in fits]
    colours = [
        'C2'
        if (result.selected is not None and f is result.selected)
        else (
            'C0'
            if f.improvement >= result.config.min_improvement and f.t >= result.config.min_t
            else 'C7'
        )
        for f in fits
    ]
    ax.barh(y, imp, color=colours)
    ax.set_yticks(y)
    ax.set_yticklabels(
        [f'{f.key}' + ('' if f.reference == 'nominal' else f' (vs {f.reference})') for f in fits],
        fontsize=8,
    )
    ax.axvline(result.config.min_improvement, color='k', ls=':', lw=0.8)
    for yy, f in zip(y, fits):
        ax.text(max(f.improvement, 0) + 0.01, yy, f't={f.t:.1f}', va='center', fontsize=7)
    ax.set_xlim(min(-0.1, min(imp) - 0.05), 1.15)
    ax.set_xlabel('held-out improvement (share of the robust prediction loss removed)')
    ax.set_title('candidate effects (green: selected; dotted: minimum effect size)', fontsize=10)
    fig.tight_layout()
    save_figure(fig, out_dir / 'naming_evidence.png', dpi=90)
    plt.close(fig)
    return 'naming_evidence.png'


def _plot_gap(replay: Replay, base, ext, out_dir, record_index, t_span=8.0):
    """Chained short-horizon predictions (nominal vs extended) of the pitch and wheel rate over
    the most informative stretch of one record, plus the per-phase gaps before/after."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    m = np.flatnonzero((replay.win_record == record_index) & replay.active)
    if m.size == 0:
        return None
    rec = replay.records[record_index]
    # non-overlapping windows: one every horizon
    t = replay.win_t[m]
    t0 = t[0]
    # the stretch with the largest nominal loss
    r0 = replay.residuals([base], m)[0]
    loss = np.mean((r0 / replay.scales) ** 2, axis=(1, 2))
    if t[-1] - t[0] > t_span:
        cs = np.array([loss[(t >= a) & (t < a + t_span)].sum() for a in t])
        t0 = t[int(np.argmax(cs))]
    chain = []
    nxt = t0
    for i, tt in zip(m, t):
        if tt >= nxt - 1e-9 and tt < t0 + t_span:
            chain.append(i)
            nxt = tt + replay.horizon
    chain = np.array(chain, int)
    _, traj = replay.predict([base, ext], chain, trajectory=True)
    fig, axes = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
    tm = (rec.t >= t0 - 0.2) & (rec.t <= t0 + t_span + 0.5)
    axes[0].plot(rec.t[tm], rec.q_base[tm], 'k', lw=0.8, label='measured')
    axes[1].plot(rec.t[tm], rec.wheel_rate[tm], 'k', lw=0.8, label='measured')
    tau = replay.substep * np.arange(traj.shape[2])
    for w, i in enumerate(chain):
        ts = replay.win_t[i] + tau
        for p, (col, lab) in enumerate((('C3', 'nominal model'), ('C2', 'extended model'))):
            axes[0].plot(ts, traj[p, w, :, 0], col, lw=1.2, label=lab if w == 0 else None)
            axes[1].plot(ts, traj[p, w, :, 3], col, lw=1.2, label=lab if w == 0 else None)
    axes[0].set_ylabel('q_base (rad)')
    axes[1].set_ylabel('wheel rate rel. body (rad/s)')
    axes[1].set_xlabel('time (s)')
    axes[0].set_title(
        f'{rec.name}: {replay.horizon:.2f} s predictions from measured states '
        '(multiple shooting), before and after'
    )
    from matplotlib.patches import Patch

    in_view = (
        (replay.win_record == record_index)
        & (replay.win_t <= t0 + t_span + 0.5)
        & (replay.win_t >= t0 - 0.2 - replay.horizon)
    )
    shown = set(replay.win_phase[in_view])
    bands = [
        Patch(facecolor=PHASE_COLOURS[p], edgecolor='0.6', label=f'phase: {p}')
        for p in PHASES
        if p in shown
    ]  # the background bands (shade_phases)
    for ax in axes:
        shade_phases(ax, replay, record_index)
        ax.legend(handles=ax.get_legend_handles_labels()[0] + bands, fontsize=8, loc='upper right')
        ax.set_xlim(t0 - 0.2, t0 + t_span + 0.5)
    fig.tight_layout()
    save_figure(fig, out_dir / 'gap_timeseries.png', dpi=90)
    plt.close(fig)
    return 'gap_timeseries.png'


def _plot_gap_bars(per_phase, out_dir):
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    phases = list(per_phase)
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
    x = np.arange(len(phases))
    for ax, key, unit in ((axes[0], 'rms_q_base', 'rad'), (axes[1], 'rms_wheel_rate', 'rad/s')):
        ax.bar(
            x - 0.2,
            [per_phase[p]['before'][key] for p in phases],
            0.4,
            color='C3',
            label='nominal',
        )
        ax.bar(
            x + 0.2,
            [per_phase[p]['after'][key] for p in phases],
            0.4,
            color='C2',
            label='extended',
        )
        ax.set_xticks(x)
        ax.set_xticklabels(phases, rotation=20)
        ax.set_title(f'RMS {key[4:]} prediction error at the horizon ({unit})')
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out_dir / 'gap_phases.png', dpi=90)
    plt.close(fig)
    return 'gap_phases.png'


# ----------------------------------------------------------------------------- pipeline


def contract(result, gaps_yaml, base) -> dict:
    """The `krang discrepancy --json` object (DESIGN.md §3) plus extra keys: gap_unit, the
    physical pitch and wheel-angle gaps, detail (link / joint of a variant), heldout_improvement.
    """
    b, a = gaps_yaml['before'], gaps_yaml['after']
    g0, g1 = b['gap'], a['gap']
    extra = {
        'gap_unit': "RMS whitened error (1 = the nominal model's typical error per signal)",
        'gap_pitch_rad': [b['rms_q_base'], a['rms_q_base']],
        'gap_wheel_rad': [b['rms_wheel'], a['rms_wheel']],
    }
    if 'gap_matched' in a:  # judged against a baseline: the figure its verdict uses
        extra['gap_matched'] = [b['gap_matched'], a['gap_matched']]
    if result.selected is None:
        return {
            'effect': 'none',
            'value': None,
            'unit': None,
            'uncertainty': None,
            'gap_before': g0,
            'gap_after': g0,
            **extra,
            'gap_pitch_rad': [b['rms_q_base'], b['rms_q_base']],
            'gap_wheel_rad': [b['rms_wheel'], b['rms_wheel']],
            'best_candidate': result.singles[0].key if result.singles else None,
            'best_heldout_improvement': result.singles[0].improvement if result.singles else None,
        }
    entries = effect_entries(result.selected, base)
    if len(entries) == 1:
        e = entries[0]
        out = {
            'effect': e['effect'],
            'value': e['value'],
            'unit': e['unit'],
            'uncertainty': e['uncertainty'],
            'gap_before': g0,
            'gap_after': g1,
            **extra,
        }
        if 'detail' in e:
            out['detail'] = e['detail']
        out['heldout_improvement'] = result.selected.improvement
        out['at_bound'] = result.selected.at_bound
        return out
    items = []
    for k, e in enumerate(entries):
        item = {
            'effect': e['effect'],
            'value': e['value'],
            'unit': e['unit'],
            'uncertainty': e['uncertainty'],
            'gap_before': g0,
            'gap_after': gaps_yaml['steps'][k],
        }
        if 'detail' in e:
            item['detail'] = e['detail']
        items.append(item)
    return {
        'effects': items,
        'gap_before': g0,
        'gap_after': g1,
        **extra,
        'at_bound': result.selected.at_bound,
        'heldout_improvement': getattr(
            result.selected, 'improvement_vs_nominal', result.selected.improvement
        ),
    }


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
) -> dict:
    """The workflow (module docstring). `measured`: paths (files/folders) or Record objects.
    `baseline`: an extended_model.yaml of earlier runs: the new data are compared with the robot as
    that file corrects it, whitened by its own typical errors there (so the gap says how far off it
    is), and the effects named are what changed.
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
    base = model.terms() if base_doc is None else load_extended_model(baseline, model.terms())[1]
    timing['load_s'] = time.perf_counter() - t
    say(f'loaded {len(records)} record(s), {sum(r.duration for r in records):.1f} s of data')
    t = time.perf_counter()
    replay = Replay(records, model, replay_config, phases)
    timing['replay_setup_s'] = time.perf_counter() - t
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
    structure = residual_structure(
        replay, extended_terms(base, result.selected), result.folds, result.blocks
    )
    timing['structure_s'] = time.perf_counter() - t
    t = time.perf_counter()
    per_record = per_record_values(replay, base, result.selected, result.config)
    drift = per_third_values(replay, base, result.selected, result.config)
    timing['per_record_s'] = time.perf_counter() - t
    split = [k for k, v in per_record.get('effects', {}).items() if v['inconsistent']]
    if split:
        say(f'per-record values disagree beyond their uncertainty: {", ".join(split)}')
    t = time.perf_counter()
    ypath = out_dir / 'extended_model.yaml'
    sources = [r.source or r.name for r in records]
    write_extended_model(
        ypath, result.selected, model, sources=sources, base=base, baseline=base_doc
    )
    _, ext_terms = load_extended_model(ypath, model.terms())
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
    verdict, reason = _verdict(
        result, structure, gaps_yaml, ref_scales is not None, drift, sitting, excess
    )
    say(f'verdict: {verdict}' + (f' ({reason})' if reason else ''))
    r1a = r1[replay.active]
    own = np.sqrt(np.median(r1a**2, axis=0) / 0.4549) + 1e-12
    extra = {
        'verdict': verdict,
        'verdict_reason': reason,
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
    js = _with_verdict(js, verdict, reason, structure, result, base)
    if base_doc is not None:
        js['baseline'] = str(baseline)
    if discretisation:
        js['discretisation'] = discretisation
    if sitting:
        js['sitting_offset'] = sitting
    if excess:
        js['gap_test'] = excess
    if per_record:
        js['per_record'] = per_record
        if split:
            js['misattribution_warning'] = (
                f'{", ".join(split)}: the records give values that differ far beyond their '
                'uncertainties (chi2/dof > 4, spread > 10 %): one robot has one value, so the '
                'effect is absorbing something else that differs between the runs'
            )
    timing['resimulate_s'] = time.perf_counter() - t
    files = []
    t = time.perf_counter()
    if plots:
        files += plot_location(loc, replay, out_dir)
        files.append(_plot_evidence(result, out_dir))
        counts = np.bincount(replay.win_record[replay.active], minlength=len(records))
        ri = int(np.argmax(counts))
        f = _plot_gap(replay, base, ext_terms, out_dir, ri)
        if f:
            files.append(f)
        files.append(_plot_gap_bars(per_phase, out_dir))
    timing['plots_s'] = time.perf_counter() - t
    t = time.perf_counter()
    _write_report(
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
        json.dump(_plain(js), f, indent=1)
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
    }


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


def _verdict(
    result, structure, gaps_yaml, referenced: bool, drift=None, sitting=None, excess=None
):
    """('unexplained' | 'named' | 'none', reason). Unexplained when the residual after the
    selected effects is still predictable by generic forces (verdict.py), when the model's pitch
    on the caster misses the measured one (``verdict.sitting_offset``), when a selected effect's
    value changes between the thirds of the records (it is not a constant of the robot), when,
    judged against a baseline, the model is still more than MAX_GAP times its error on the
    baseline's own data off, phase for phase (``verdict.phase_matched_gap``), or, judged on its
    own yardstick, when its gap on the balancing windows exceeds what a right model shows
    (``verdict.gap_test``)."""
    if structure.significant:
        return 'unexplained', (
            'the residual after the library effects is still structured: ' + structure.sentence()
        )
    if (sitting or {}).get('off'):
        return 'unexplained', (
            f'the pitch on the caster is {sitting["pooled"]:+.4f} rad off the model after the '
            'library effects (model-free: the caster geometry, the wheel radius, the floor slope '
            f'and the IMU bias set it; tolerance {SITTING_TOL:g} rad)'
        )
    moving = [k for k, v in (drift or {}).get('effects', {}).items() if v['inconsistent']]
    if moving:
        v = drift['effects'][moving[0]]
        return 'unexplained', (
            f'{", ".join(moving)} changes in time: fitted on the first, middle and last thirds '
            'of the records it is '
            + ', '.join(f'{x:.4g}' for x in v['values'])
            + f' {v["unit"]} (chi2/dof {v["chi2_per_dof"]:.1f}): not a constant of the robot'
        )
    after = gaps_yaml['after']
    gap = after.get('gap_matched', after['gap'])
    if referenced and gap > MAX_GAP:
        return 'unexplained', (
            f"the model is still {gap:.3g}x its error on the baseline's own data off after the "
            'library effects, phase for phase (more than ' + f'{MAX_GAP:g}x)'
        )
    if not referenced and (excess or {}).get('exceeds'):
        return 'unexplained', (
            'the model is further off than a right model is after the library effects: '
            + gap_sentence(excess)
        )
    return ('none' if result.selected is None else 'named'), ''


def _with_verdict(js, verdict, reason, structure, result, base):
    """The JSON with the verdict: 'unexplained' replaces the name (the library effects that were
    fitted are kept as 'partial', with the share they explain)."""
    js = dict(js)
    js['signature'] = structure.as_dict()
    if verdict != 'unexplained':
        return js
    partial = js.get('effects') or (
        [{k: js[k] for k in ('effect', 'value', 'unit', 'uncertainty')}]
        if js.get('effect') not in (None, 'none')
        else []
    )
    out = {
        'effect': 'unexplained',
        'value': None,
        'unit': None,
        'uncertainty': None,
        'gap_before': js['gap_before'],
        'gap_after': js['gap_after'],
        'reason': reason,
        'partial': partial,
        'partial_heldout_improvement': (
            None if result.selected is None else result.selected.improvement
        ),
    }
    for k, v in js.items():
        if k not in out and k not in ('effect', 'effects', 'value', 'unit', 'uncertainty'):
            out[k] = v
    return out


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


def _f(v, digits=4):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return 'n/a'
    return f'{v:.{digits}g}'


def _write_report(
    path, records, replay, loc, result, gaps_yaml, per_phase, heldout, js, files, model, timing
):
    L = []
    cfg = result.config
    L.append('# Discrepancy report: simulation vs measured data\n')
    if js.get('effect') == 'unexplained':
        L.append(
            '**Finding: unexplained** — ' + js['reason'] + '. The library effects fitted anyway '
            '(kept in extended_model.yaml as the best partial correction): '
            + (
                ', '.join(f'{e["effect"]} = {e["value"]:.4g} {e["unit"]}' for e in js['partial'])
                or 'none'
            )
            + '.\n'
        )
    elif result.selected is None:
        L.append(
            '**Finding: none** — no effect of the library improves the held-out predictions by '
            'the minimum '
            'effect size.\n'
        )
    else:
        items = js['effects'] if 'effects' in js else [js]
        L.append(
            '**Finding: '
            + ' + '.join(
                f'{e["effect"]} = {e["value"]:.4g} ± {e["uncertainty"]:.2g} {e["unit"]}'
                + (
                    f' ({", ".join(f"{k} {v}" for k, v in e["detail"].items())})'
                    if e.get('detail')
                    else ''
                )
                for e in items
            )
            + '**\n'
        )
    if js.get('misattribution_warning'):
        L.append('**Warning (misattributed effect?):** ' + js['misattribution_warning'] + '.\n')
        L.append('| effect | ' + ' | '.join(js['per_record']['groups']) + ' | chi2/dof |')
        L.append('|---|' + '---|' * (len(js['per_record']['groups']) + 1))
        for k, v in js['per_record']['effects'].items():
            L.append(
                f'| {k} ({v["unit"]}) | '
                + ' | '.join(f'{x:.4g} ± {u:.2g}' for x, u in zip(v['values'], v['uncertainties']))
                + f' | {v["chi2_per_dof"]:.1f} |'
            )
        L.append('')
    if js.get('baseline'):
        L.append(
            f'Judged against the baseline `{js["baseline"]}`: the gap is in units of that '
            "model's typical error on its own data (1 = as good as there); the effects named "
            'are what changed since, on top of it.\n'
        )
    g0, g1 = gaps_yaml['before']['gap'], gaps_yaml['after']['gap']
    b, a = gaps_yaml['before'], gaps_yaml['after']
    L.append(
        f'Gap (RMS whitened error of the {replay.horizon:.3g} s predictions over the four '
        f'signals, fitting '
        f"phases; 1 = the nominal model's typical error): **{_f(g0, 3)} before, {_f(g1, 3)} "
        f'after** '
        f'(shrunk x{_f(g0 / g1 if g1 else math.nan, 3)}). Pitch error at the horizon '
        f'{_f(b["rms_q_base"], 3)} -> '
        f'{_f(a["rms_q_base"], 3)} rad, wheel angle {_f(b["rms_wheel"], 3)} -> '
        f'{_f(a["rms_wheel"], 3)} rad; '
        f'held-out robust loss {_f(heldout["before"], 3)} -> {_f(heldout["after"], 3)}.\n'
    )
    if 'gap_matched' in a:
        L.append(
            "Phase for phase against the baseline's own errors (the verdict's figure, 1 = as "
            f'good as there): {_f(b["gap_matched"], 3)} before, {_f(a["gap_matched"], 3)} after.\n'
        )
    L.append('## Data\n')
    L.append(
        '| record | source | kind | duration (s) | sample period (s) | windows (fitting / all) |'
    )
    L.append('|---|---|---|---|---|---|')
    for i, r in enumerate(records):
        m = replay.win_record == i
        L.append(
            f'| {r.name} | {r.source} | {r.kind} | {r.duration:.1f} | {r.period:.4f} | '
            f'{int((m & replay.active).sum())} / {int(m.sum())} |'
        )
    L.append('')
    L.append(
        f'Nominal model: `krang_model.wip` with beta `{model.beta_source}`, wheel radius '
        f'{model.drive.wheel_radius} m, Kt {model.drive.torque_constant} N m/A x '
        f'{model.drive.gear_ratio}, '
        f'viscous {model.drive.viscous_friction} N m s, Coulomb {model.drive.coulomb_friction} N '
        f'm. '
        f'Replay: {replay.horizon:.3g} s predictions from every measured state (stride '
        f'{replay.cfg.stride_s} s), {len(replay.eval_steps)} comparison points, sub-step '
        f'{replay.substep * 1e3:.2f} ms; fitting phases: {", ".join(replay.phases)}.\n'
    )
    L.append('## 1. Where the model and the data disagree (nominal model)\n')
    for s in loc.summary:
        L.append(f'- {s}')
    L.append('')
    L.append(
        '| phase | windows | mean loss | '
        + ' | '.join(f'{c} bias / RMS ({u})' for c, u in zip(CHANNELS, CHANNEL_UNITS))
        + ' |'
    )
    L.append('|---|---|---|' + '---|' * len(CHANNELS))
    for ph, st in loc.phase_stats.items():
        L.append(
            f'| {ph} | {st["windows"]} | {st["mean_loss"]:.3g} | '
            + ' | '.join(
                f'{st[c]["bias"]:+.2e} / {st[c]["rms"]:.2e} (z {st[c]["bias_z"]:+.1f})'
                for c in CHANNELS
            )
            + ' |'
        )
    L.append('')
    L.append(
        'Decorrelation time of the errors: '
        + ', '.join(f'{c} {loc.decorrelation_s[c]:.2f} s' for c in CHANNELS)
        + f' (horizon {replay.horizon:.2f} s).\n'
    )
    if loc.hotspots:
        L.append('Worst stretches (whitened loss > 3x median for >= 0.5 s):\n')
        L.append('| record | from (s) | to (s) | phase | channel | loss / median |')
        L.append('|---|---|---|---|---|---|')
        for h in loc.hotspots[:8]:
            L.append(
                f'| {h["record"]} | {h["t0"]:.2f} | {h["t1"]:.2f} | {h["phase"]} | {h["channel"]} '
                f'| {h["loss_x_median"]:.1f} |'
            )
        L.append('')
    if loc.statics.get('points'):
        L.append(
            'Steady state (quiet balancing; at rest the pitch equation says commanded torque = '
            'gravity '
            'torque M g l sin(theta) for the nominal model):\n'
        )
        L.append(
            '| record | rest (s) | q_base at rest (rad) | model balance q_base (rad) | commanded '
            'torque (N m) | '
            'model gravity torque (N m) |'
        )
        L.append('|---|---|---|---|---|---|')
        for p in loc.statics['points']:
            L.append(
                f'| {p["record"]} | {p["rest_s"]:.1f} | {p["q_base"]:.4f} | '
                f'{p["model_balance_q_base"]:.4f} | '
                f'{p["tau_cmd"]:+.2f} ± {p["tau_cmd_std"]:.2f} | {p["gravity_torque"]:+.2f} |'
            )
        L.append('')
        if 'slope' in loc.statics:
            st = loc.statics
            L.append(
                f'Line fit across records: commanded = {st["slope"]:.2f} ± {st["slope_se"]:.2f} x '
                f'gravity '
                f'{st["intercept"]:+.2f} ± {st["intercept_se"]:.2f} N m, R^2 = {st["r2"]:.2f} '
                f'(nominal: 1 x + 0): torque scale {st["torque_scale"]:.2f}, zero-torque pitch '
                f'offset '
                f'{st["offset_angle"]:+.4f} rad.\n'
            )
    for f in files:
        if f.startswith('locate_'):
            L.append(f'![{f}]({f})')
    L.append('')
    L.append('## 2. Naming the missing effect\n')
    L.append(
        f'Each candidate is fitted on all fitting windows (value, cluster-robust uncertainty) and '
        f'on '
        f'{cfg.folds} interleaved folds of {cfg.block_s} s blocks; each fold fit predicts the '
        f'blocks it did not '
        f'see. Accept: held-out improvement >= {cfg.min_improvement} of the robust loss AND '
        f'paired t over blocks '
        f'(log loss ratio) >= {cfg.min_t}; combinations must improve on the accepted set by the '
        f'same margins.\n'
    )
    L.append(
        '| candidate | value | uncertainty (1 sigma) | held-out improvement | t | blocks better | '
        'at bound | vs |'
    )
    L.append('|---|---|---|---|---|---|---|---|')
    for f in result.singles + result.combos:
        s = f.summary()
        vals = ', '.join(f'{e["value"]:.4g} {e["unit"]}' for e in s['effects'])
        unc = ', '.join(f'{e["uncertainty"]:.2g}' for e in s['effects'])
        mark = ' **(selected)**' if f is result.selected else ''
        L.append(
            f'| {f.key}{mark} | {vals} | {unc} | {f.improvement:+.3f} | {f.t:.1f} | '
            f'{f.blocks_better:.2f} | '
            f'{"yes" if f.at_bound else ""} | {f.reference} |'
        )
    L.append('')
    amb = ambiguity(result)
    if amb:
        L.append(amb + '\n')
    if result.selected is not None and result.selected.at_bound:
        L.append(
            '**Warning:** a selected value sits at the end of its search range. The effect '
            'improves the '
            'predictions, but the data ask for more than the effect can physically give: read it '
            'as a sign '
            'that the model is misspecified in a way the library does not name, not as a measured '
            'value.\n'
        )
    if 'naming_evidence.png' in files:
        L.append('![naming_evidence.png](naming_evidence.png)\n')
    L.append('## 3. The extended model and the gap\n')
    L.append(
        '`extended_model.yaml` holds the effects with their values and `sim_effects`, the keyword '
        'arguments '
        'of `krang_sim.physics.SimEffects` that make the simulator carry them. The gap after is '
        'computed by '
        're-simulating every window with the model read back from that file.\n'
    )
    L.append(
        '| phase | windows | '
        + ' | '.join(f'{c} RMS before -> after ({u})' for c, u in zip(CHANNELS, CHANNEL_UNITS))
        + ' |'
    )
    L.append('|---|---|' + '---|' * len(CHANNELS))
    for ph, g in per_phase.items():
        L.append(
            f'| {ph} | {g["before"]["windows"]} | '
            + ' | '.join(
                f'{g["before"]["rms_" + c]:.3g} -> {g["after"]["rms_" + c]:.3g}' for c in CHANNELS
            )
            + ' |'
        )
    L.append(
        f'| **fitting phases** | {b["windows"]} | '
        + ' | '.join(f'**{b["rms_" + c]:.3g} -> {a["rms_" + c]:.3g}**' for c in CHANNELS)
        + ' |'
    )
    L.append('')
    for f in files:
        if f.startswith('gap_'):
            L.append(f'![{f}]({f})')
    L.append('')
    L.append('## JSON\n')
    L.append('```json\n' + json.dumps(_plain(js)) + '\n```\n')
    L.append('Stage timings (s): ' + ', '.join(f'{k} {v:.2f}' for k, v in timing.items()) + '\n')
    write_text(path, '\n'.join(L))


def ambiguity(result) -> str:
    """A sentence when the runner-up explains the data almost as well as the selected effect."""
    if result.selected is None or len(result.singles) < 2:
        return ''
    sel = result.selected if len(result.selected.effects) == 1 else None
    if sel is None:
        return ''
    others = [f for f in result.singles if f is not sel and f.improvement > 0.5 * sel.improvement]
    if not others:
        return ''
    from .naming import _compare

    act = np.isfinite(sel.heldout_loss)
    msgs = []
    for o in others[:3]:
        imp, t, _ = _compare(o.heldout_loss, sel.heldout_loss, result.blocks, act)
        msgs.append(f'{o.key} (held-out loss {imp:.0%} lower with {sel.key}, t = {t:.1f})')
    return (
        'Runner-up explanations and how well the data separate them from the selected one: '
        + '; '.join(msgs)
        + '. t >= 3 means the data distinguish them.'
    )
