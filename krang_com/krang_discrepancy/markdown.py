"""DIR/report.md: the finding, the data, where the model and the data disagree, the naming's
evidence, the extended model and the gap, the JSON."""

from __future__ import annotations

import json
import math

import numpy as np

from krang_model.files import write_text

from .evidence import compare
from .extended_model import plain
from .record import CHANNEL_UNITS, CHANNELS


def _f(v, digits=4):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return 'n/a'
    return f'{v:.{digits}g}'


def write_report(
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
    for k, v in (js.get('dropped_changing') or {}).items():
        L.append(
            f'**Dropped partner {k}:** its value changes between the thirds of the records ('
            + ', '.join(f'{x:.4g}' for x in v['values'])
            + f' {v["unit"]}, chi2/dof {v["chi2_per_dof"]:.1f}); the rest was refitted without it '
            'and judged again.\n'
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
    widened = f'; {replay.widened()}' if replay.widened() else ''
    L.append(
        f'Nominal model: `krang_model.wip` with beta `{model.beta_source}`, wheel radius '
        f'{model.drive.wheel_radius} m, Kt {model.drive.torque_constant} N m/A x '
        f'{model.drive.gear_ratio}, '
        f'viscous {model.drive.viscous_friction} N m s, Coulomb {model.drive.coulomb_friction} N '
        f'm. '
        f'Replay: {replay.horizon:.3g} s predictions from every measured state (stride '
        f'{replay.stride_s:.3g} s{widened}), {len(replay.eval_steps)} comparison points, '
        f'sub-step {replay.substep * 1e3:.2f} ms; fitting phases: {", ".join(replay.phases)}.\n'
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
        '`extended_model.yaml` holds the effects with their values (`krang experiment table2 '
        '--extended-model` simulates the robot it describes). The gap after is computed by '
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
    L += closed_loop_section(js, files)
    L.append('## JSON\n')
    L.append('```json\n' + json.dumps(plain(js)) + '\n```\n')
    L.append('Stage timings (s): ' + ', '.join(f'{k} {v:.2f}' for k, v in timing.items()) + '\n')
    write_text(path, '\n'.join(L))


#: the closed-loop figures of the report: (key, heading, unit, digits)
CLOSED_LOOP_ROWS = (
    ('lift_off_s', 'lift-off after the stand command', 's', 3),
    ('settle_time_s', 'time until resting (8 cm)', 's', 3),
    ('resting_displacement_m', 'resting position', 'm', 3),
    ('resting_pitch_rad', 'resting pitch', 'rad', 4),
    ('peak_electrical_power_w', 'peak electrical power', 'W', 3),
    ('mean_resting_electrical_power_w', 'mean resting electrical power', 'W', 3),
)


def closed_loop_section(js, files) -> list:
    """The closed-loop check's section (``closed_loop_check``), when it ran."""
    cl = js.get('closed_loop')
    if not cl:
        return []
    g0, g1 = cl['gap']['before'], cl['gap']['after']
    lo = cl['lift_off_gap_s']
    L = ["## 4. Closed loop: does the model's robot stand up as the real one did?\n"]
    L.append(
        'Each run replayed in closed loop under the controller that made it, on the reduced plant '
        'with the nominal model (before) and the extended model (after). '
        + '; '.join(f'{k}: {v}' for k, v in cl['definitions'].items())
        + '.\n'
    )
    L.append('| gap | before (nominal) | after (extended) |')
    L.append('|---|---|---|')
    L.append(f'| one-step gap (whitened) | {_f(js["gap_before"])} | {_f(js["gap_after"])} |')
    L.append(
        f'| runs that stood up (measured {g0["measured_stood_up"]} of {g0["runs"]}) | '
        f'{g0["stood_up"]} | {g1["stood_up"]} |'
    )
    L.append(
        f'| runs that came to rest balanced (measured {g0["measured_balanced"]}) | '
        f'{g0["balanced"]} | {g1["balanced"]} |'
    )
    L.append(f'| stand-ups missed | {g0["missed_stand_up"]} | {g1["missed_stand_up"]} |')
    L.append(
        f'| worst lift-off error (s) | {_f(g0["lift_off_worst_s"], 3)} | '
        f'{_f(g1["lift_off_worst_s"], 3)} |'
    )
    L.append(
        '| lift-off gap the verdict reads (s) | '
        + ' | '.join('missed' if v is None else _f(v, 3) for v in lo)
        + ' |'
    )
    for key, head, unit, _ in CLOSED_LOOP_ROWS:
        L.append(f'| median abs. error, {head} ({unit}) | {_f(g0[key], 3)} | {_f(g1[key], 3)} |')
    L.append('')
    L.append(
        '| run | '
        + ' | '.join(
            f'{head} ({unit}): measured / nominal / extended'
            for _, head, unit, _ in CLOSED_LOOP_ROWS
        )
        + ' |'
    )
    L.append('|---|' + '---|' * len(CLOSED_LOOP_ROWS))
    for run in cl['runs']:
        L.append(
            f'| {run["name"]} | '
            + ' | '.join(
                ' / '.join(_f(run[k].get(key), d) for k in ('measured', 'before', 'after'))
                for key, _, _, d in CLOSED_LOOP_ROWS
            )
            + ' |'
        )
    L.append('')
    for f in files:
        if f.startswith('closed_loop'):
            L.append(
                f'![{f}]({f})\n\nIMU pitch over time from the stand command: measured (black), '
                'the nominal model in closed loop (red, dashed), the extended model (green); dots '
                'mark each lift-off, the dotted line the lift-off level.'
            )
    L.append('')
    return L


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
    act = np.isfinite(sel.heldout_loss)
    msgs = []
    for o in others[:3]:
        imp, t, _ = compare(o.heldout_loss, sel.heldout_loss, result.blocks, act)
        msgs.append(f'{o.key} (held-out loss {imp:.0%} lower with {sel.key}, t = {t:.1f})')
    return (
        'Runner-up explanations and how well the data separate them from the selected one: '
        + '; '.join(msgs)
        + '. t >= 3 means the data distinguish them.'
    )

