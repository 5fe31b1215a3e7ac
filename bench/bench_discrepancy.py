"""Time a full `krang discrepancy` run on a 60 s record and the share of each stage.

The record is simulated (synthetic.simulate_record on the closed loop: ADRC, sit -> stand ->
balance with pose changes and a current excitation; a hidden floor slope of 0.02 rad); its
generation is timed separately and is not part of the workflow. The workflow runs as the CLI
would, with the whole library, plots and report.

    .venv/bin/python bench/bench_discrepancy.py [--seconds 60] [--stride 0.05] [--no-plots] [--csv
    FILE]

--csv runs the workflow on a hardware log instead (e.g. balancing_runs/table2/beta190_trial0.csv).
--validate prints the per-effect validation table of docs/discrepancy.md instead (the settings of
krang_com/test/test_discrepancy.py: 22 s records, seed 3, one hidden effect each, plus no effect).
--hidden [--plant reduced|mujoco] runs krang_discrepancy.synthetic.VALIDATION_SUITE (no-effect
seeds and noise levels, small effects, pairs, effects outside the library), or with --plant mujoco
its MUJOCO_SUITE (records of the full-body plant): answer, values, 2-sigma coverage, false names,
and for an unexplained answer the partial correction and the rules that fired.
--null N runs N no-effect records (seeds 101.., noise x0.5, x1, x2) and counts false names: the
selection rule's false-positive rate on records.
--gap-null N [--design suite|30hz|long] [--seed S] the gap test's null distribution
(verdict.gap_test): N fresh no-effect records (noise x0.5, x1, x2 in turn), the nominal model's gap
on the balancing windows of each, its 99th percentile and how many exceed verdict.MAX_OWN_GAP; and
its pitch on the caster, which must miss by more than verdict.SITTING_TOL to open the sitting route
of the selection rule (naming._admit_by_sitting).
Designs: the suite's 22 s records; 22 s records whose controller runs and logs at 30 Hz like the
hardware's (default pose delay); 30 s records that sit down at the end, at the default stride.
--verdicts N [--seed S] runs N in-library records with known truth (verdict_cases: one or two
library effects at drawn sizes, or none; seeds from 7001) through the workflow and counts how
often each rule of the verdict fires (verdict.RULES) and how many are answered unexplained.
--plant mujoco makes them with the full-body plant; --poses held without the pose programme.
--closed-loop N [--seed S] [--plant reduced|mujoco] the closed-loop rule (closed_loop_stand_up) on
N records made under the 2018 controller with known truth (seeds from 7401): does it refuse the
true model, or the workflow's?
--real KIT [--stride S] [--out DIR] runs the baseline on all Table II runs of the kit at KIT
(balancing_runs/table2) and judges one new-tyre run against it (stride 0.1 s unless given), with
wall and CPU time (the process, its threads and its worker processes), the parameter sets predicted
(in how many batched predictions, and as element sub-steps), the peak memory of all of them
together, the load average and a reference measured in the same run; --out keeps their outputs
(DIR/table2, DIR/new).
"""

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'krang_com'))


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument('--seconds', type=float, default=60.0)
    ap.add_argument('--stride', type=float, default=None)
    ap.add_argument('--no-plots', action='store_true')
    ap.add_argument('--csv', default=None)
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--validate', action='store_true')
    ap.add_argument('--hidden', action='store_true')
    ap.add_argument('--real', metavar='KIT', default=None)
    ap.add_argument('--out', metavar='DIR', default=None)
    ap.add_argument('--null', type=int, default=0, metavar='N')
    ap.add_argument('--gap-null', type=int, default=0, metavar='N')
    ap.add_argument('--verdicts', type=int, default=0, metavar='N')
    ap.add_argument('--design', default='suite', choices=('suite', '30hz', 'long'))
    ap.add_argument('--plant', default='reduced', choices=('reduced', 'mujoco'))
    ap.add_argument('--poses', default='programme', choices=('programme', 'held'))
    ap.add_argument('--closed-loop', type=int, default=0, metavar='N')
    args = ap.parse_args(argv)
    if args.closed_loop:
        seed = args.seed if args.seed != 1 else 7401
        return closed_loop_rates(args.closed_loop, seed, args.plant)
    if args.gap_null:
        return gap_null(args.gap_null, args.seed if args.seed != 1 else 1001, args.design)
    if args.verdicts:
        return verdicts(
            args.verdicts, args.seed if args.seed != 1 else 7001, args.plant, args.poses
        )
    if args.validate:
        return validate(args.seed if args.seed != 1 else 3)
    if args.null:
        return null_records(args.null, args.seed if args.seed != 1 else 101)
    if args.hidden:
        return hidden(args.plant)
    if args.real:
        return real(
            Path(args.real),
            args.stride if args.stride is not None else 0.1,
            None if args.out is None else Path(args.out),
        )

    from krang_discrepancy.loaders import load_csv_record
    from krang_discrepancy.replay import ReplayConfig
    from krang_discrepancy.synthetic import simulate_record
    from krang_discrepancy.report import run_discrepancy

    t0 = time.perf_counter()
    if args.csv:
        rec = load_csv_record(args.csv)
        cfg = ReplayConfig(stride_s=args.stride or 0.05)
        what = f'hardware log {Path(args.csv).name}'
    else:
        rec = simulate_record({'floor_slope': 0.02}, seconds=args.seconds, seed=args.seed)
        cfg = ReplayConfig(stride_s=args.stride or 0.05, pose_delay_s=0.01)
        what = 'simulated record, hidden floor_slope 0.02 rad'
    gen = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as out:
        t1 = time.perf_counter()
        res = run_discrepancy([rec], out, replay_config=cfg, plots=not args.no_plots)
        total = time.perf_counter() - t1
    timing = res['timing']
    rp = res['replay']
    print(
        f'{what}: {rec.duration:.1f} s at {1 / rec.period:.0f} Hz, {len(rp)} windows '
        f'({int(rp.active.sum())} fitting), horizon {rp.horizon:.2f} s, sub-step '
        f'{rp.substep * 1e3:.2f} ms'
    )
    if not args.csv:
        print(f'record generation (not part of the workflow): {gen:.2f} s')
    print(f'full discrepancy run: {total:.2f} s')
    for k, v in timing.items():
        print(f'  {k:16s} {v:7.2f} s  {100 * v / total:5.1f} %')
    nt = res['result'].timing
    print('  naming detail: ' + ', '.join(f'{k} {v:.2f} s' for k, v in nt.items()))
    print(
        f'  predictions: {rp.timing.get("predict_calls", 0)} batched calls, '
        f'{rp.timing.get("predict_sets", 0)} parameter sets, {rp.timing.get("predict_s", 0):.2f} s'
    )
    print(
        'result: '
        + json.dumps(
            {
                k: res['json'][k]
                for k in ('effect', 'value', 'gap_before', 'gap_after')
                if k in res['json']
            }
        )
    )
    return 0


def validate(seed):
    from krang_model.effects import nominal_drive
    from krang_discrepancy.nominal import NominalModel
    from krang_discrepancy.replay import Replay, ReplayConfig
    from krang_discrepancy.synthetic import simulate_record
    from krang_discrepancy.naming import gaps, name_effects

    cases = [
        ('none', None, None),
        ('imu_pitch_bias', {'imu_pitch_bias': 0.02}, 0.02),
        ('floor_slope', {'floor_slope': 0.02}, 0.02),
        ('wheel_radius', {'wheel_radius': 0.25}, 0.25),
        ('payload', {'payload@lGripper': 5.0}, 5.0),
        ('wheel_viscous_friction', {'wheel_viscous_friction': 2.0}, 2.0),
        ('wheel_coulomb_friction', {'wheel_coulomb_friction': 2.0}, 2.0),
        ('torque_constant', {'torque_constant': 0.8}, 0.8 * nominal_drive().torque_constant),
        ('actuation_delay', {'actuation_delay': 0.02}, 0.02),
        ('encoder_offset', {'encoder_offset@JWaist': 0.05}, 0.05),
        ('rolling_resistance', {'rolling_resistance': 4.0}, 4.0),
    ]
    model = NominalModel.default()
    print(
        '| hidden | true value | named | value +- 1 sigma | error | held-out improvement | t | '
        'runner-up (improvement) '
        '| gap before -> after | naming (s) |'
    )
    print('|---|---|---|---|---|---|---|---|---|---|')
    for name, hidden, truth in cases:
        rec = simulate_record(hidden, seconds=22.0, seed=seed, hold_s=2.0, sit_down=False)
        rp = Replay([rec], model, ReplayConfig(pose_delay_s=0.01, stride_s=0.1))
        t = time.perf_counter()
        res = name_effects(rp)
        dt = time.perf_counter() - t
        g = gaps(rp, model.terms(), res)
        sel = res.selected
        if sel is None:
            best = res.singles[0]
            print(
                f'| {name} | - | none | - | - | best {best.key}: {best.improvement:+.3f} | '
                f'{best.t:.1f} | - | '
                f'{g["before"]["gap"]:.3f} -> {g["after"]["gap"]:.3f} | {dt:.1f} |'
            )
            continue
        e = sel.effects[0]
        v, unit = e.display(float(sel.values[0]))
        u = float(sel.uncertainty[0]) * e.display_scale()
        ru = [f for f in res.singles if f is not sel][0]
        err = f'{100 * (v - truth) / truth:+.2f} %' if truth else '-'
        print(
            f'| {name} | {truth:.4g} {unit} | {res.name} | {v:.5g} +- {u:.2g} | {err} | '
            f'{sel.improvement:.3f} | '
            f'{sel.t:.1f} | {ru.key} ({ru.improvement:.3f}) | {g["before"]["gap"]:.3f} -> '
            f'{g["after"]["gap"]:.3f} '
            f'(x{g["before"]["gap"] / g["after"]["gap"]:.1f}) | {dt:.1f} |'
        )
    return 0


def hidden_case(case, seconds=22.0):
    """Run one VALIDATION_SUITE (or MUJOCO_SUITE) case; returns a dict with the answer and the
    checks. An eighth field gives more keywords of ``simulate_record`` (the plant, the pose
    programme, plant options). The replay's pose delay is the reduced plant's (it re-reduces a
    moving pose every 20 ms, §9 of docs/discrepancy.md); the MuJoCo plant has no such lag."""
    import math
    from dataclasses import replace
    from krang_discrepancy.replay import ReplayConfig
    from krang_discrepancy.report import run_discrepancy
    from krang_discrepancy.synthetic import Unmodelled, simulate_record
    from krang_model.effects import library
    from krang_sim.sensors import SensorNoise

    cid, fx, um, seed, noise_k, truth, equivalents = case[:7]
    extra = dict(case[7]) if len(case) > 7 else {}
    plant = extra.get('plant', 'reduced')
    delay = 0.01 if plant == 'reduced' else 0.0
    base = SensorNoise()
    noise = replace(
        base,
        imu_pitch_std_rad=base.imu_pitch_std_rad * noise_k,
        gyro_std_rad_s=base.gyro_std_rad_s * noise_k,
        joint_std_rad=base.joint_std_rad * noise_k,
    )
    rec = simulate_record(
        fx,
        seed=seed,
        seconds=seconds,
        hold_s=2.0,
        sit_down=False,
        unmodelled=Unmodelled(**um),
        noise=noise,
        **extra,
    )
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        res = run_discrepancy(
            [rec], out, plots=False, replay_config=ReplayConfig(pose_delay_s=delay, stride_s=0.1)
        )
        secs = time.perf_counter() - t0
    js = res['json']
    items = js.get('effects') or ([js] if js['effect'] not in ('none', 'unexplained') else [])
    named = {e['effect']: e for e in items}
    if truth:
        expected = set(truth)
        right = set(named) == expected
    else:
        hidden_any = um or fx or extra.get('plant_options')
        expected = {'unexplained', *equivalents} if hidden_any else {'none'}
        answer = (
            js['effect'] if js['effect'] in ('none', 'unexplained') else '+'.join(sorted(named))
        )
        right = answer in expected
    partial = {e['effect']: e for e in js.get('partial') or []}

    def checks_of(found):
        out = []
        for name, parameter in truth.items():
            # the suite states parameters (a torque constant's scale); the report gives values
            true = next(e for e in library() if e.name == name).display(parameter)[0]
            if name in found:
                e = found[name]
                err = e['value'] - true
                out.append(
                    {
                        'effect': name,
                        'true': true,
                        'value': e['value'],
                        'sigma': e['uncertainty'],
                        'rel_err': err / true,
                        'z': err / e['uncertainty'] if e['uncertainty'] else math.inf,
                    }
                )
        return out

    checks = checks_of(named)
    false = sorted(set(named) - set(truth)) if truth else (sorted(named) if right is False else [])
    return {
        'case': cid,
        'answer': js['effect'] if not items else '+'.join(e['effect'] for e in items),
        'right': right,
        'checks': checks,
        'false_names': false,
        'seconds': secs,
        'gap': (js['gap_before'], js['gap_after']),
        'rules': js.get('rules_fired', {}),
        'dropped_changing': sorted(js.get('dropped_changing', {})),
        'reason': js.get('reason', ''),
        # an `unexplained` answer's partial correction: the library's effects fitted anyway
        'partial': sorted(partial),
        'partial_right': bool(partial) and set(partial) == set(truth),
        'partial_checks': checks_of(partial),
        'gap_test': (js.get('gap_test') or {}).get('gap'),
        'lift_off_gap_s': (js.get('closed_loop') or {}).get('lift_off_gap_s'),
    }


def hidden(plant='reduced'):
    """The suite of the plant: VALIDATION_SUITE (reduced) or MUJOCO_SUITE. With an `unexplained`
    answer the partial correction and its values are shown too, and the rules that fired."""
    from krang_discrepancy.synthetic import MUJOCO_SUITE, VALIDATION_SUITE

    rows = []
    print(
        '| case | answer | right | values (rel. error, z = error/sigma) | partial correction | '
        'rules fired | gap | s |'
    )
    print('|---|---|---|---|---|---|---|---|')
    for case in VALIDATION_SUITE if plant == 'reduced' else MUJOCO_SUITE:
        r = hidden_case(case)
        rows.append(r)
        vals = _values(r['checks'])
        part = '+'.join(r['partial']) or '-'
        if r['partial_checks']:
            part += ': ' + _values(r['partial_checks'])
        fired = ', '.join(k for k, v in r['rules'].items() if v) or '-'
        print(
            f'| {r["case"]} | {r["answer"]} | {"yes" if r["right"] else "**no**"} | {vals} | '
            f'{part} | {fired} | {r["gap"][0]:.3g} -> {r["gap"][1]:.3g} | {r["seconds"]:.1f} |',
            flush=True,
        )
    part = [c for r in rows for c in r['partial_checks']]
    print(
        f'unexplained {sum(r["answer"] == "unexplained" for r in rows)}/{len(rows)}, with the '
        f'truth as the partial correction {sum(r["partial_right"] for r in rows)}; its values '
        f'within 5 %: {sum(abs(c["rel_err"]) <= 0.05 for c in part)}/{len(part)}'
    )
    checks = [c for r in rows for c in r['checks']]
    print(
        f'named right {sum(r["right"] for r in rows)}/{len(rows)}; values within 5 %: '
        f'{sum(abs(c["rel_err"]) <= 0.05 for c in checks)}/{len(checks)}; within 2 sigma: '
        f'{sum(abs(c["z"]) <= 2 for c in checks)}/{len(checks)}; false names: '
        f'{sum(len(r["false_names"]) for r in rows)} '
        f'({", ".join(n for r in rows for n in r["false_names"]) or "-"})'
    )
    return 0


def _values(checks):
    return '; '.join(
        f'{c["effect"]} {c["value"]:.4g} ({c["rel_err"]:+.1%}, z {c["z"]:+.1f})' for c in checks
    )


def null_records(n, first_seed):
    """The selection rule's false-positive rate on records: n no-effect records (seeds from
    first_seed, sensor noise x0.5, x1, x2 in turn) through the whole workflow; a false name is any
    named effect. Prints each answer, the count and the 95 % upper bound of the rate."""
    false = 0
    for i in range(n):
        seed, k = first_seed + i, (0.5, 1.0, 2.0)[i % 3]
        r = hidden_case((f'none seed {seed}, noise x{k:g}', {}, {}, seed, k, {}, ()))
        false += not r['right'] and r['answer'] != 'unexplained'
        print(f'{r["case"]}: {r["answer"]} ({r["seconds"]:.1f} s)', flush=True)
    upper = 1.0 - 0.05 ** (1.0 / n) if false == 0 else math.nan
    print(
        f'false names on {false} of {n} no-effect records'
        + (f' (95 % upper bound of the rate {upper:.1%})' if false == 0 else '')
    )
    return 0


#: sizes of the in-library effects of ``--verdicts`` (parameters as ``model_terms`` takes them),
#: drawn uniformly (with a random sign where both signs are physical): none of them is a size of
#: the suite or of the tests
VERDICT_SIZES = {
    'imu_pitch_bias': (0.006, 0.03, True),
    'floor_slope': (0.006, 0.03, True),
    'wheel_radius': (0.25, 0.29, False),
    'payload@lGripper': (2.0, 8.0, False),
    'payload@rGripper': (2.0, 8.0, False),
    'wheel_viscous_friction': (1.0, 4.0, False),
    'wheel_coulomb_friction': (0.5, 3.0, False),
    'torque_constant': (0.7, 0.93, False),
    'actuation_delay': (0.01, 0.06, False),
    'encoder_offset@JWaist': (0.02, 0.08, True),
    'rolling_resistance': (3.0, 8.0, False),
}


def verdict_cases(n, first_seed, plant='reduced', poses='programme'):
    """n in-library records with known truth: one library effect (two in every third record, none
    in every seventh) at a size drawn from ``VERDICT_SIZES``; seed = first_seed + i; made by
    `plant`, with the suite's pose programme or the poses held (``poses``)."""
    import numpy as np

    keys = sorted(VERDICT_SIZES)
    cases = []
    for i in range(n):
        seed = first_seed + i
        rng = np.random.default_rng(seed)
        k = 0 if i % 7 == 6 else (2 if i % 3 == 2 else 1)
        fx = {}
        for key in rng.choice(keys, size=k, replace=False):
            lo, hi, signed = VERDICT_SIZES[key]
            v = float(rng.uniform(lo, hi))
            if key == 'wheel_radius' and abs(v - 0.2667) < 0.006:
                v += 0.012
            fx[str(key)] = -v if signed and rng.random() < 0.5 else v
        if 'payload@lGripper' in fx and 'payload@rGripper' in fx:
            fx.pop('payload@rGripper')
        noise = (0.5, 1.0, 2.0)[i % 3]
        truth = {key.split('@')[0]: v for key, v in fx.items()}
        extra = {'plant': plant, **({'programme': ()} if poses == 'held' else {})}
        cases.append(
            (
                f'seed {seed}: {fx or "none"}, noise x{noise:g}',
                fx,
                {},
                seed,
                noise,
                truth,
                (),
                extra,
            )
        )
    return cases


def verdicts(n, first_seed, plant='reduced', poses='programme'):
    """The verdict's rules on in-library records with known truth (``verdict_cases``): how often
    each rule fires, and the false-``unexplained`` rate (an in-library record answered
    ``unexplained``), with its 95 % upper bound."""
    from krang_discrepancy.verdict import RULES

    rows = []
    for case in verdict_cases(n, first_seed, plant, poses):
        r = hidden_case(case)
        rows.append(r)
        fired = ', '.join(k for k, v in r['rules'].items() if v) or '-'
        part = ''
        if r['answer'] == 'unexplained':
            part = f'; partial {"+".join(r["partial"]) or "-"} {_values(r["partial_checks"])}'
        print(
            f'{r["case"]}: {r["answer"]} ({"right" if r["right"] else "WRONG"}) '
            f'{_values(r["checks"])}{part}; rules fired: '
            f'{fired}; dropped (changing): {", ".join(r["dropped_changing"]) or "-"}; gap test '
            f'{r["gap_test"] or math.nan:.3f}; lift-off gap {r["lift_off_gap_s"]}; '
            f'{r["seconds"]:.1f} s',
            flush=True,
        )
    m = len(rows)
    unexplained = sum(r['answer'] == 'unexplained' for r in rows)
    print(f'{m} in-library records: named right {sum(r["right"] for r in rows)}/{m}')
    print(f'false unexplained {unexplained}/{m} ({_upper(unexplained, m)})')
    for rule in RULES:
        k = sum(bool(r['rules'].get(rule)) for r in rows)
        print(f'  {rule}: fired on {k}/{m} ({_upper(k, m)})')
    k = sum(bool(r['dropped_changing']) for r in rows)
    print(f'  a changing partner dropped on {k}/{m}')
    k = sum(r['partial_right'] for r in rows)
    print(f'  answered unexplained with the truth as the partial correction: {k}/{m}')
    checks = [c for r in rows for c in r['checks']]
    print(
        f'  values of the named effects within 5 %: '
        f'{sum(abs(c["rel_err"]) <= 0.05 for c in checks)}/{len(checks)}, within 2 sigma: '
        f'{sum(abs(c["z"]) <= 2 for c in checks)}/{len(checks)}'
    )
    return 0


def closed_loop_rates(n, first_seed, plant):
    """The closed-loop rule (``verdict.closed_loop_fails``, rule ``closed_loop_stand_up``) on
    records whose truth is known, made as the hardware logs were: the 2018 controller
    (``closed_loop_check.hardware_2018_config``: the paper-era stand PD at 30 Hz), 24 s (sit 1 s,
    stand, hold the pose; long enough for the rest interval), one library effect drawn from
    ``VERDICT_SIZES`` (none in every fourth record), made by `plant`. As on beta_16 (and in
    test_discrepancy_closed_loop.py) the controller's beta puts the CoM 17 mm forward of the
    true robot's and the pose sits at a CoM angle of -0.09 rad for it, so the robot leaves the
    caster only as the stand PD's current builds up (the lift-off depends on the drive train).
    ``run_discrepancy`` replays a synthetic record under the controller that
    ``simulate_record`` uses by default, so here the check is called with the 2018 controller
    explicitly, on (a) the TRUE model (the rule's own false rate: a right model refused) and (b)
    the workflow's extended model (its answer on the record, without the closed-loop stage)."""
    import numpy as np

    from krang_discrepancy.closed_loop_check import closed_loop_check, hardware_2018_config
    from krang_discrepancy.extended_model import load_extended_model
    from krang_discrepancy.nominal import NominalModel
    from krang_discrepancy.replay import ReplayConfig
    from krang_discrepancy.report import run_discrepancy
    from krang_discrepancy.synthetic import simulate_record
    from krang_discrepancy.verdict import MAX_LIFT_OFF_GAP_S, closed_loop_fails
    from krang_model.effects import model_terms
    from krang_sim.scenarios import TABLE2_POSE, shifted_beta, stand_pose

    keys = (
        'torque_constant',
        'wheel_coulomb_friction',
        'wheel_viscous_friction',
        'rolling_resistance',
        'wheel_radius',
        'actuation_delay',
        'floor_slope',
        'imu_pitch_bias',
    )
    cfg = hardware_2018_config()
    model = NominalModel.default()
    ctl_beta = shifted_beta(model.robot, model.beta, TABLE2_POSE, 0.017)
    pose = stand_pose(model.robot, ctl_beta, target_theta_rad=-0.09)
    fires_true = fires_named = named_right = 0
    for i in range(n):
        seed = first_seed + i
        rng = np.random.default_rng(seed)
        fx = {}
        if i % 4 != 3:
            key = keys[int(rng.integers(len(keys)))]
            lo, hi, signed = VERDICT_SIZES[key]
            v = float(rng.uniform(lo, hi))
            fx[key] = -v if signed and rng.random() < 0.5 else v
        rec = simulate_record(
            fx,
            seconds=24.0,
            seed=seed,
            start_pose=pose,
            programme=(),
            excitation_a=0.0,
            sit_down=False,
            controller_config=cfg,
            controller_beta=ctl_beta,
            plant=plant,
        )
        truth = model_terms(fx, model.terms())
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            res = run_discrepancy(
                [rec],
                out,
                plots=False,
                replay_config=ReplayConfig(stride_s=0.1),
                closed_loop=False,
            )
            named = load_extended_model(Path(out) / 'extended_model.yaml')
            closed = closed_loop_check(
                [rec],
                model,
                truth,
                named,
                controller_config=cfg,
                controller_beta=ctl_beta,
                others={'nominal': model.terms()},
            )
            secs = time.perf_counter() - t0
        js = res['json']
        items = js.get('effects') or ([js] if js['effect'] not in ('none', 'unexplained') else [])
        answer = js['effect'] if not items else '+'.join(e['effect'] for e in items)
        right = {e['effect'] for e in items} == set(fx) or (not fx and answer == 'none')
        # the verdict reads the extended model's lift-off gap: [nominal, model] pairs
        gap_true, gap_named = closed['lift_off_gap_s']
        f_true = closed_loop_fails({'lift_off_gap_s': [None, gap_true]})
        f_named = closed_loop_fails({'lift_off_gap_s': [None, gap_named]})
        fires_true += f_true
        fires_named += f_named
        named_right += right
        run = closed['runs'][0]
        lift = {k: run[k].get('lift_off_s') for k in ('measured', 'before', 'after', 'nominal')}
        print(
            f'seed {seed}: {fx or "none"} -> {answer} ({"right" if right else "WRONG"}); '
            f'lift-off (s) measured {_f(lift["measured"])}, true model {_f(lift["before"])}, '
            f'named model {_f(lift["after"])}, nominal {_f(lift["nominal"])}; measured '
            f'balanced {run["measured"]["balanced"]}, true {run["before"]["balanced"]}, named '
            f'{run["after"]["balanced"]}; rule fires on the true model {f_true}, on the named '
            f'{f_named}; {secs:.1f} s',
            flush=True,
        )
    print(
        f'{n} records ({plant} plant, 2018 controller): closed_loop_stand_up (lift-off within '
        f'{MAX_LIFT_OFF_GAP_S:g} s, at rest balanced) fires on the TRUE model '
        f"{fires_true}/{n} ({_upper(fires_true, n)}), on the workflow's model {fires_named}/{n} "
        f'({_upper(fires_named, n)}); the workflow named the truth on {named_right}/{n}'
    )
    return 0


def _f(v):
    return '-' if v is None else f'{v:.3f}'


def _upper(k, n):
    """The rate k/n and, for k = 0, its 95 % upper bound."""
    if k == 0:
        return f'0 %, below {1.0 - 0.05 ** (1.0 / n):.1%} at 95 %'
    return f'{k / n:.1%}'


def gap_null(n, first_seed, design):
    """The gap test's null distribution (module docstring, --gap-null): no naming is needed,
    since on a no-effect record the gap after the (no) named effects is the nominal model's."""
    from dataclasses import replace

    import numpy as np
    from krang_discrepancy.nominal import NominalModel
    from krang_discrepancy.replay import Replay, ReplayConfig
    from krang_discrepancy.synthetic import record_controller_config, simulate_record
    from krang_discrepancy.verdict import MAX_OWN_GAP, SITTING_TOL, gap_test, sitting_offset
    from krang_sim.sensors import SensorNoise

    model = NominalModel.default()
    # the logs' 30 Hz, as the nearest whole number of 1 ms physics steps (33 ms)
    at_30hz = record_controller_config({'rate_hz': 1000 / 33, 'detector.rate_hz': 1000 / 33})
    base = SensorNoise()
    gaps, sits = [], []
    for i in range(n):
        seed, k = first_seed + i, (0.5, 1.0, 2.0)[i % 3]
        noise = replace(
            base,
            imu_pitch_std_rad=base.imu_pitch_std_rad * k,
            gyro_std_rad_s=base.gyro_std_rad_s * k,
            joint_std_rad=base.joint_std_rad * k,
        )
        if design == 'long':
            rec = simulate_record(None, seed=seed, seconds=30.0, hold_s=2.5, noise=noise)
            cfg = ReplayConfig(pose_delay_s=0.01)
        else:
            rec = simulate_record(
                None,
                seed=seed,
                seconds=22.0,
                hold_s=2.0,
                sit_down=False,
                noise=noise,
                controller_config=at_30hz if design == '30hz' else None,
            )
            delay = {} if design == '30hz' else {'pose_delay_s': 0.01}  # the logs' own timing
            cfg = ReplayConfig(stride_s=0.1, **delay)
        rp = Replay([rec], model, cfg)
        r0 = rp.residuals([model.terms()])[0]
        rp.set_scales(r0)
        g = gap_test(rp, r0)['gap']
        sit = abs(sitting_offset(rp, model.terms())['pooled'])
        gaps.append(g)
        sits.append(sit)
        print(
            f'seed {seed}, noise x{k:g}: gap on the balancing windows {g:.4f}, pitch on the '
            f'caster off by {1e3 * sit:.2f} mrad',
            flush=True,
        )
    gaps = np.array(gaps)
    print(
        f'{design}: {n} records, gap {gaps.min():.3f}-{gaps.max():.3f}, median '
        f'{np.median(gaps):.3f}, 99th percentile {np.percentile(gaps, 99):.3f}; above '
        f'MAX_OWN_GAP {MAX_OWN_GAP:g}: {int(np.sum(gaps > MAX_OWN_GAP))} of {n}; pitch on the '
        f'caster off by at most {1e3 * max(sits):.2f} mrad, more than SITTING_TOL '
        f'{1e3 * SITTING_TOL:g} mrad on {sum(x > SITTING_TOL for x in sits)} of {n}'
    )
    return 0


def real(kit, stride, keep=None):
    """The Table II baseline (all 20 runs pooled) and one new-tyre run judged against it
    (one_gain_beta128_trial1), as `krang discrepancy` runs them (no plots; their outputs in
    `keep`/table2 and `keep`/new when given, to compare answers): wall and CPU time
    (this process, all threads, and its worker processes), peak memory (this process, and at most
    that of the largest worker per worker), the machine's load average, and the CPU time in units
    of one nominal prediction of every baseline window measured in the same run (a figure that
    the machine's load does not change)."""
    import os
    import resource

    from krang_discrepancy.loaders import load_measured
    from krang_discrepancy.nominal import NominalModel
    from krang_discrepancy.replay import PREDICTED, Replay, ReplayConfig
    from krang_discrepancy.report import run_discrepancy

    cfg = ReplayConfig(stride_s=stride)
    runs = kit / 'balancing_runs'

    def clock():
        cpu = 0.0
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
            r = resource.getrusage(who)
            cpu += r.ru_utime + r.ru_stime
        return (
            time.perf_counter(),
            cpu,
            PREDICTED['sets'],
            PREDICTED['calls'],
            PREDICTED['element_steps'],
        )

    print('load average at the start: ' + ', '.join(f'{x:.2f}' for x in os.getloadavg()))
    model = NominalModel.default()
    unit_rp = Replay(load_measured([runs / 'table2']), model, cfg)
    w0, c0, *_ = clock()
    unit_rp.predict([model.terms()], windows=slice(0, 1))
    w1, c1, *_ = clock()
    print(
        f'the compiled batch integrator (krang_model.wip_batch) ready in {w1 - w0:.2f} s wall, '
        f'{c1 - c0:.2f} s CPU (compiled on first use, about 1.5 s, then loaded from its on-disk '
        'cache); the figures below exclude it'
    )
    w0, c0, *_ = clock()
    unit_rp.predict([model.terms()])
    w1, c1, *_ = clock()
    unit = c1 - c0
    print(
        f'reference: one nominal prediction of the {len(unit_rp)} baseline windows '
        f'(stride {stride:g} s): {w1 - w0:.2f} s wall, {unit:.2f} s CPU'
    )
    del unit_rp
    sampler = _MemorySampler()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) if keep is None else keep
        w0, c0, s0, n0, e0 = clock()
        a = run_discrepancy(
            [runs / 'table2'], Path(out) / 'table2', replay_config=cfg, plots=False
        )
        w1, c1, s1, n1, e1 = clock()
        new = runs / 'new_tire' / 'one_gain_beta128_trial1.csv'
        if not new.exists():
            new = sorted((runs / 'new_tire').glob('*.csv'))[0]
        b = run_discrepancy(
            [new],
            Path(out) / 'new',
            replay_config=cfg,
            plots=False,
            baseline=Path(out) / 'table2' / 'extended_model.yaml',
        )
        w2, c2, s2, n2, e2 = clock()
    sampler.stop()
    for label, res, wall, cpu, sets, calls, elements in (
        ('baseline: all Table II runs', a, w1 - w0, c1 - c0, s1 - s0, n1 - n0, e1 - e0),
        (f'judged: {new.name} against it', b, w2 - w1, c2 - c1, s2 - s1, n2 - n1, e2 - e1),
    ):
        print(
            f'{label}: {wall:.1f} s wall, {cpu:.1f} s CPU ({cpu / unit:.0f} x the reference), '
            f'{sets} parameter sets in {calls} batched predictions, '
            f'{elements / 1e9:.3f} billion element sub-steps; ' + json.dumps(_brief(res['json']))
        )
        print(f'  where its wall time went: {_where(res, wall)}')
    print(
        f'peak memory of this process and its workers together {sampler.peak / 2**20:.0f} MB '
        f'(sampled every {sampler.period:g} s; this process alone '
        f'{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB); '
        f'{a["replay"].workers} threads and worker processes'
    )
    print('load average at the end: ' + ', '.join(f'{x:.2f}' for x in os.getloadavg()))
    return 0


class _MemorySampler:
    """The largest resident memory of this process and its child processes together, sampled
    from /proc every `period` s in a thread (ru_maxrss of children counts the parent's pages a
    child had before it replaced its image)."""

    def __init__(self, period=0.2):
        import os
        import threading

        self.period, self.peak = period, 0
        self._stop = threading.Event()
        self._pid = os.getpid()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _rss(self, pid):
        try:
            with open(f'/proc/{pid}/status') as f:
                kb = next(int(line.split()[1]) for line in f if line.startswith('VmRSS:'))
        except (OSError, StopIteration, ValueError):
            return 0
        return 1024 * kb

    def _children(self, pid):
        import glob

        out = []
        for path in glob.glob(f'/proc/{pid}/task/*/children'):
            try:
                with open(path) as f:
                    out += [int(c) for c in f.read().split()]
            except OSError:
                pass
        return out

    def _run(self):
        while not self._stop.wait(self.period):
            pids, total = [self._pid], 0
            while pids:
                pid = pids.pop()
                total += self._rss(pid)
                pids += self._children(pid)
            self.peak = max(self.peak, total)

    def stop(self):
        self._stop.set()
        self._thread.join()


def _where(res, wall):
    """The workflow's stages (``run_discrepancy``'s timing, with the naming's own split) in s of
    wall time; the closed-loop stage is the wait for its worker processes."""
    t, n = res['timing'], res['result'].timing
    split = ', '.join(
        f'{k[:-2]} {n[k]:.1f}' for k in ('nominal_s', 'scan_s', 'singles_s', 'combos_s') if k in n
    )
    parts = [
        f'{k[:-2]} {v:.1f}' + (f' ({split})' if k == 'naming_s' else '')
        for k, v in t.items()
        if v >= 0.05
    ]
    return ', '.join(parts) + f'; outside the stages {wall - sum(t.values()):.1f}'


def _brief(js):
    keep = (
        'effect',
        'value',
        'unit',
        'uncertainty',
        'effects',
        'partial',
        'gap_before',
        'gap_after',
        'reason',
        'dropped_changing',
    )
    return {k: js[k] for k in keep if k in js}


if __name__ == '__main__':
    sys.exit(main())
