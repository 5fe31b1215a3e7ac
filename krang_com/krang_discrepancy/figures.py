"""The figures of the report: the naming evidence, the chained predictions before and after, the
per-phase gaps (the location figures are ``krang_discrepancy.locate``'s)."""

from __future__ import annotations

import numpy as np

from krang_model.files import save_figure

from .locate import PHASE_COLOURS, shade_phases
from .phases import PHASES
from .replay import Replay


def plot_evidence(result, out_dir):
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


def plot_gap(replay: Replay, base, ext, out_dir, record_index, t_span=8.0):
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


def plot_gap_bars(per_phase, out_dir):
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


#: the closed-loop figure's curves: (key of the check's traces, label, colour, line style)
CLOSED_LOOP_CURVES = (
    ('measured', 'measured (the real robot)', 'k', '-'),
    ('before', 'nominal model, closed loop', 'C3', '--'),
    ('after', 'extended model, closed loop', 'C2', '-'),
)


def plot_closed_loop(closed, out_dir, names=None, filename='closed_loop.png', t_span=12.0):
    """Measured vs simulated pitch over time, one panel per run (``names``, default: up to four,
    the first run of each name stem such as beta16_*): the measured log (black), the closed-loop
    replay with the nominal model (red, dashed) and with the extended one (green); time from the
    stand command; dots mark each lift-off, the dotted line is the lift-off level (sitting pitch +
    the check's ``lift_rad``). Other models' traces in the check (keys beyond the three) are
    drawn thin."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    runs = {r['name']: r for r in closed['runs']}
    if names is None:
        stems, names = set(), []
        for n in runs:
            stem = n.split('_')[0]
            if stem not in stems and runs[n]['measured']['stood_up'] and len(names) < 4:
                stems.add(stem)
                names.append(n)
        names = names or list(runs)[:4]
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 2.4 * len(names) + 0.6), squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        tr, run = closed['traces'][name], runs[name]
        main = [c[0] for c in CLOSED_LOOP_CURVES]
        extra = [k for k in tr if k not in main]
        curves = list(CLOSED_LOOP_CURVES) + [
            (k, k, f'C{4 + i}', '-.') for i, k in enumerate(extra)
        ]
        for key, label, colour, style in curves:
            if key not in tr:
                continue
            t, q = tr[key]
            keep = (t >= -1.0) & (t <= t_span)
            lw = 1.4 if key in main else 0.9
            ax.plot(t[keep], q[keep], color=colour, ls=style, lw=lw, label=label)
            m = run.get(key, {})
            if m.get('lift_off_s') is not None:
                lo = m['lift_off_s']
                ax.plot([lo], [np.interp(lo, t, q)], 'o', color=colour, ms=5)
        q_sit = run['measured'].get('sitting_pitch_rad')
        if q_sit is not None:
            lift = q_sit + closed['lift_rad']
            ax.axhline(lift, color='0.5', ls=':', lw=0.8, label='lift-off level')
        words = ', '.join(
            f'{k} {run[k]["lift_off_s"]:.2f} s'
            if run[k].get('lift_off_s') is not None
            else f'{k} never'
            for k in ('measured', 'before', 'after')
        )
        ax.set_title(f'{name}: lift-off {words}', fontsize=9)
        ax.set_ylabel('IMU pitch q_base (rad)', fontsize=8)
        ax.set_xlim(-1.0, t_span)
    axes[0, 0].legend(fontsize=7, loc='lower right')
    axes[-1, 0].set_xlabel('time since the stand command (s)')
    fig.tight_layout()
    save_figure(fig, out_dir / filename, dpi=90)
    plt.close(fig)
    return filename
