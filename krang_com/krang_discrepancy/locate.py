"""Locate the disagreement before explaining it: which signals, when, in which phase.

``locate(replay)`` replays every window (sitting included) under the nominal model and summarises
the prediction errors at the horizon:

* per phase (sitting, standing_up, balancing, moving_joints, sitting_down) and channel (q_base,
  pitch_rate, wheel, wheel_rate): number of windows, bias (mean error), RMS, robust RMS, the bias's
  significance (bias / standard error with the effective sample size of autocorrelated windows),
  and the whitened RMS (in units of the robust scale of the fitting phases, so channels compare);
* autocorrelation of each channel's error sequence (per record, consecutive windows): lag-1 value
  and the decorrelation time (first lag below 1/e). White errors decorrelate within a horizon;
  a missing physical effect gives errors correlated over seconds;
* hot spots: stretches of at least 0.5 s where the windows' whitened loss stays above 3x its
  median, with their phase and the channel that dominates.

``plot_location`` draws the residual time series with phase shading, the per-phase bars and the
autocorrelations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from krang_model.wip import reduce_pose
from krang_model.files import save_figure

from .phases import PHASES
from .record import CHANNEL_UNITS, CHANNELS
from .replay import Replay

PHASE_COLOURS = {
    'sitting': '#d9d9d9',
    'standing_up': '#fdd0a2',
    'balancing': '#ffffff',
    'moving_joints': '#c6dbef',
    'sitting_down': '#fcbba1',
}


@dataclass
class Location:
    residuals: np.ndarray  # (S, E, 4) nominal, all windows
    loss: np.ndarray  # (S,) robust whitened loss per window
    phase_stats: dict  # phase -> channel -> stats
    acf: dict  # channel -> (lags_s, acf)
    decorrelation_s: dict  # channel -> s
    hotspots: list  # dicts
    statics: dict = field(default_factory=dict)  # rest points and their line fit
    summary: list = field(default_factory=list)  # plain-language findings


def autocorrelation(x, max_lag):
    x = x - x.mean()
    den = float(x @ x)
    if den <= 0 or x.size < 3:
        return np.zeros(max_lag + 1)
    return np.array(
        [1.0] + [float(x[:-k] @ x[k:]) / den if k < x.size else 0.0 for k in range(1, max_lag + 1)]
    )


def locate(replay: Replay, terms=None, max_lag_s: float = 5.0) -> Location:
    terms = terms if terms is not None else replay.model.terms()
    res = replay.residuals([terms])[0]
    if replay.scales is None:
        replay.set_scales(res)
    loss = replay.window_loss(res[None])[0]
    stride = (
        float(np.median(np.diff(replay.win_t[replay.win_record == replay.win_record[0]])))
        if len(replay) > 1
        else 1.0
    )
    max_lag = max(1, int(round(max_lag_s / stride)))
    # autocorrelation per channel, averaged over records (weighted by windows)
    acf, decor = {}, {}
    for c, name in enumerate(CHANNELS):
        acc, wsum = np.zeros(max_lag + 1), 0
        for ri in np.unique(replay.win_record):
            m = replay.win_record == ri
            x = res[m, -1, c]
            if x.size > 3:
                acc += x.size * autocorrelation(x, max_lag)
                wsum += x.size
        a = acc / max(wsum, 1)
        acf[name] = (np.arange(max_lag + 1) * stride, a)
        below = np.flatnonzero(a < 1.0 / math.e)
        decor[name] = float(below[0] * stride) if below.size else float(max_lag * stride)
    # per-phase statistics
    stats = {}
    for ph in PHASES:
        m = replay.win_phase == ph
        if not np.any(m):
            continue
        stats[ph] = {
            'windows': int(m.sum()),
            'seconds': float(m.sum() * stride),
            'mean_loss': float(loss[m].mean()),
        }
        for c, name in enumerate(CHANNELS):
            x = res[m, -1, c]
            a1 = acf[name][1][1] if len(acf[name][1]) > 1 else 0.0
            n_eff = max(1.0, x.size * (1 - a1) / (1 + a1)) if abs(a1) < 1 else 1.0
            sd = float(np.std(x, ddof=1)) if x.size > 1 else math.nan
            bias = float(np.mean(x))
            stats[ph][name] = {
                'bias': bias,
                'rms': float(np.sqrt(np.mean(x**2))),
                'robust_rms': float(np.sqrt(np.median(x**2) / 0.4549)),
                'bias_z': bias / (sd / math.sqrt(n_eff)) if sd and sd > 0 else math.nan,
                'whitened_rms': float(np.sqrt(np.mean((x / replay.scales[-1, c]) ** 2))),
                'unit': CHANNEL_UNITS[c],
            }
    # hot spots
    med = (
        float(np.median(loss[replay.active])) if np.any(replay.active) else float(np.median(loss))
    )
    hot = loss > 3.0 * med
    spots = []
    for ri, seg in hot_stretches(replay, hot):
        t0, t1 = replay.win_t[seg[0]], replay.win_t[seg[-1]] + replay.horizon
        z = np.mean((res[seg] / replay.scales) ** 2, axis=(0, 1))
        phases, counts = np.unique(replay.win_phase[seg], return_counts=True)
        spots.append(
            {
                'record': replay.records[ri].name,
                't0': float(t0),
                't1': float(t1),
                'phase': str(phases[np.argmax(counts)]),
                'channel': CHANNELS[int(np.argmax(z))],
                'loss_x_median': float(loss[seg].mean() / med),
            }
        )
    spots.sort(key=lambda s: -s['loss_x_median'] * (s['t1'] - s['t0']))
    loc = Location(res, loss, stats, acf, decor, spots, statics(replay))
    loc.summary = _summarise(loc, replay)
    return loc


def hot_stretches(replay: Replay, hot, windows=None, min_s: float = 0.5) -> list:
    """[(record index, window indices)] of every run of consecutive `hot` windows of one record
    lasting at least `min_s` (first window's start to the last one's end). `windows`: the windows
    that count (default all); one left out ends a run."""
    windows = np.ones(len(hot), dtype=bool) if windows is None else windows
    out = []
    for ri in np.unique(replay.win_record):
        idx = np.flatnonzero(windows & (replay.win_record == ri))
        i = 0
        while i < idx.size:
            if not hot[idx[i]]:
                i += 1
                continue
            j = i + 1
            while j < idx.size and hot[idx[j]] and idx[j] == idx[j - 1] + 1:
                j += 1
            seg = idx[i:j]
            i = j
            if replay.win_t[seg[-1]] + replay.horizon - replay.win_t[seg[0]] >= min_s:
                out.append((int(ri), seg))
    return out


def statics(replay: Replay, terms=None, min_rest_s: float = 2.0, rate_tol: float = 0.02) -> dict:
    """Steady state, independent of inertia and timing: in every record's quiet balancing (pitch
    and ground-wheel rates below `rate_tol` for at least `min_rest_s` in all), the mean base pitch,
    the mean commanded total wheel torque, and the nominal model's gravity torque M g l sin(theta)
    there (theta from the measured pitch). At rest the pitch equation says applied torque = gravity
    torque, so across records tau_cmd = a M g l sin(theta) + c with a = 1 and c = 0 for the nominal
    model; a = 1/s for a torque scale s (torque_constant), c = -a M g l delta for an IMU pitch bias
    (or CoM angle error) delta. Friction on the wheel-ground side (floor, tyres) holds the wheel
    equation and scatters the rest points along that line rather than off it."""
    model = replay.model
    terms = terms if terms is not None else model.terms()
    pts = []
    for ri, rec in enumerate(replay.records):
        lab = replay._recs[ri].labels
        quiet = (
            (lab == 'balancing')
            & (np.abs(rec.pitch_rate) < rate_tol)
            & (np.abs(rec.wheel_rate + rec.pitch_rate) < rate_tol)
        )
        if quiet.sum() * rec.period < min_rest_s:
            continue
        body = reduce_pose(model.robot, rec.joints[quiet].mean(axis=0), model.beta)
        mgl = body.mass * model.drive.gravity * body.com_distance
        theta = rec.q_base[quiet] - terms.imu_pitch_bias + body.com_offset
        scale = terms.drive.torque_constant / model.drive.torque_constant
        tau = rec.total_torque_at(rec.t[quiet]) * scale
        pts.append(
            {
                'record': rec.name,
                'rest_s': float(quiet.sum() * rec.period),
                'q_base': float(rec.q_base[quiet].mean()),
                'model_balance_q_base': float(-body.com_offset),
                'theta': float(theta.mean()),
                'tau_cmd': float(tau.mean()),
                'tau_cmd_std': float(tau.std()),
                'gravity_torque': float(np.mean(mgl * np.sin(theta))),
                'mgl': float(mgl),
            }
        )
    out = {'points': pts}
    if len(pts) >= 3:
        x = np.array([p['gravity_torque'] for p in pts])
        y = np.array([p['tau_cmd'] for p in pts])
        if np.ptp(x) > 0:
            A = np.column_stack([x, np.ones_like(x)])
            coef, *_ = np.linalg.lstsq(A, y, rcond=None)
            resid = y - A @ coef
            dof = max(len(pts) - 2, 1)
            cov = np.linalg.inv(A.T @ A) * float(resid @ resid) / dof
            a, c = coef
            mgl = float(np.mean([p['mgl'] for p in pts]))
            out.update(
                slope=float(a),
                slope_se=float(np.sqrt(cov[0, 0])),
                intercept=float(c),
                intercept_se=float(np.sqrt(cov[1, 1])),
                r2=float(1 - resid @ resid / np.sum((y - y.mean()) ** 2)),
                torque_scale=float(1.0 / a) if a > 0 else math.nan,
                offset_angle=float(-c / (a * mgl)) if a > 0 else math.nan,
            )
    return out


def _summarise(loc: Location, replay: Replay) -> list:
    out = []
    fit_ph = [p for p in replay.phases if p in loc.phase_stats]
    if not fit_ph:
        return ['no standing or balancing phase in the data']
    worst = max(loc.phase_stats, key=lambda p: loc.phase_stats[p]['mean_loss'])
    out.append(
        f'largest disagreement in phase "{worst}" (mean whitened loss '
        f'{loc.phase_stats[worst]["mean_loss"]:.2f} vs '
        + ', '.join(
            f'{p} {loc.phase_stats[p]["mean_loss"]:.2f}' for p in loc.phase_stats if p != worst
        )
        + ')'
    )
    for p in fit_ph:
        st = loc.phase_stats[p]
        sig = [(c, st[c]['bias_z']) for c in CHANNELS if abs(st[c]['bias_z']) > 3]
        if sig:
            out.append(
                f'{p}: systematic (biased) errors in '
                + ', '.join(
                    f'{c} ({st[c]["bias"]:+.3g} {st[c]["unit"]}, z = {z:+.1f})' for c, z in sig
                )
            )
    slow = [c for c in CHANNELS if loc.decorrelation_s[c] > 3 * replay.horizon]
    if slow:
        out.append(
            'errors stay correlated for longer than the horizon in '
            + ', '.join(f'{c} ({loc.decorrelation_s[c]:.2f} s)' for c in slow)
            + ': structure, not noise'
        )
    else:
        out.append('errors decorrelate within a few horizons in every channel (noise-like)')
    st = loc.statics
    if 'slope' in st:
        out.append(
            f'statics over {len(st["points"])} records at rest: commanded torque = '
            f'{st["slope"]:.2f} '
            f'(+-{st["slope_se"]:.2f}) x model gravity torque {st["intercept"]:+.1f} '
            f'(+-{st["intercept_se"]:.1f}) N m '
            f'(R^2 {st["r2"]:.2f}); the nominal model says 1 x + 0: the torque acting is '
            f'{st["torque_scale"]:.2f} of the commanded one, and the pitch at zero torque is off '
            f'by '
            f'{st["offset_angle"]:+.3f} rad'
        )
    if loc.hotspots:
        h = loc.hotspots[0]
        out.append(
            f'worst stretch: {h["record"]} {h["t0"]:.1f}-{h["t1"]:.1f} s ({h["phase"]}, '
            f'{h["channel"]}, {h["loss_x_median"]:.1f}x the median loss); {len(loc.hotspots)} '
            f'stretches in all'
        )
    return out


# ----------------------------------------------------------------------------- plots


def shade_phases(ax, replay: Replay, record_index: int = 0):
    m = replay.win_record == record_index
    t, ph = replay.win_t[m], replay.win_phase[m]
    if t.size == 0:
        return
    i = 0
    while i < t.size:
        j = i
        while j + 1 < t.size and ph[j + 1] == ph[i]:
            j += 1
        ax.axvspan(
            t[i],
            t[j] + (t[1] - t[0] if t.size > 1 else 0),
            color=PHASE_COLOURS.get(ph[i], 'w'),
            alpha=0.6,
            lw=0,
            zorder=0,
        )
        i = j + 1


def plot_location(loc: Location, replay: Replay, out_dir, record_index=None) -> list:
    """PNG figures: residual time series (the record with the most fitting windows), per-phase
    whitened RMS and bias, autocorrelations. Returns the file names."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch
    from pathlib import Path

    out_dir = Path(out_dir)
    files = []
    if record_index is None:
        counts = np.bincount(replay.win_record[replay.active], minlength=len(replay.records))
        record_index = int(np.argmax(counts))
    m = replay.win_record == record_index
    rec = replay.records[record_index]
    fig, axes = plt.subplots(5, 1, figsize=(11, 10), sharex=True)
    axes[0].plot(rec.t, rec.q_base, 'k', lw=0.8)
    axes[0].set_ylabel('q_base (rad)')
    axes[0].set_title(
        f'{rec.name}: nominal-model prediction error at the {replay.horizon:.2f} s horizon'
    )
    for c, name in enumerate(CHANNELS):
        ax = axes[c + 1]
        ax.plot(replay.win_t[m], loc.residuals[m, -1, c], '.', ms=2, color='C%d' % c)
        ax.axhline(0, color='k', lw=0.5)
        ax.set_ylabel(f'{name}\n({CHANNEL_UNITS[c]})')
    for ax in axes:
        shade_phases(ax, replay, record_index)
    axes[-1].set_xlabel('time (s)')
    fig.legend(
        handles=[Patch(color=PHASE_COLOURS[p], label=p) for p in PHASES],
        loc='lower center',
        ncol=5,
    )
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    save_figure(fig, out_dir / 'locate_timeseries.png', dpi=90)
    plt.close(fig)
    files.append('locate_timeseries.png')
    # per-phase bars
    phases = [p for p in PHASES if p in loc.phase_stats]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    w = 0.8 / len(CHANNELS)
    for c, name in enumerate(CHANNELS):
        x = np.arange(len(phases)) + (c - 1.5) * w
        axes[0].bar(x, [loc.phase_stats[p][name]['whitened_rms'] for p in phases], w, label=name)
        axes[1].bar(
            x,
            [loc.phase_stats[p][name]['bias'] / replay.scales[-1, c] for p in phases],
            w,
            label=name,
        )
    for ax, title in zip(
        axes, ('whitened RMS error at the horizon', 'whitened bias at the horizon')
    ):
        ax.set_xticks(np.arange(len(phases)))
        ax.set_xticklabels(phases, rotation=20)
        ax.set_title(title)
        ax.axhline(0, color='k', lw=0.5)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out_dir / 'locate_phases.png', dpi=90)
    plt.close(fig)
    files.append('locate_phases.png')
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for c, name in enumerate(CHANNELS):
        lag, a = loc.acf[name]
        ax.plot(lag, a, label=f'{name} ({loc.decorrelation_s[name]:.2f} s)')
    ax.axhline(1 / math.e, color='k', ls=':', lw=0.8)
    ax.axvline(replay.horizon, color='grey', ls='--', lw=0.8)
    ax.set_xlabel('lag (s)')
    ax.set_ylabel('autocorrelation')
    ax.set_title('prediction-error autocorrelation (dashed: horizon)')
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out_dir / 'locate_acf.png', dpi=90)
    plt.close(fig)
    files.append('locate_acf.png')
    return files
