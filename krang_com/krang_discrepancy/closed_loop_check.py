"""Closed-loop check of a model: does the robot it describes do what the real robot did?

A one-step (multiple-shooting) gap says how well a model predicts 0.3 s ahead from every measured
state. It cannot say whether the robot the model describes, under the controller that made the
logs, stands up as the real one did: a model can shrink the one-step gap and still not lift off
its caster. This check replays each measured run in CLOSED LOOP on the reduced plant
(``krang_sim.plant``) with a model's effects applied, under the controller the run was made with,
and compares what both robots did, on the same definitions:

* lift-off: the stand command is the first sample with a commanded current above
  ``COMMAND_A``; the robot has lifted off when its pitch has left the caster for good, the last
  upward crossing of the sitting pitch + ``LIFT_RAD`` before the pitch first rises
  ``STAND_RISE_RAD`` above the sitting pitch (which it does only when it stands up). The
  crossing is interpolated between samples. The sitting pitch is the median before the command.
* time until resting, resting position, peak and resting power: ``krang_adrc_controller.metrics.
  physical_metrics`` (the 8 cm settle band, the rest point over 20-55 s after motion start, power
  from the COMMANDED currents of both wheels with the nominal Kt x gear: mechanical |tau w| with
  the wheels' speed relative to the body, electrical R i^2 + tau w), on the measured log and on
  the simulated one alike. Currents are commanded on both sides, so the powers compare what the
  two controllers asked for, not what the drives delivered.

The controller of a kit hardware log (``kind == 'hardware_csv'``) is the 2018 one
(``hardware_2018_config``): the paper-era stand PD (250, 40, 4, 10) for the whole run, at the
logs' ~30 Hz, with the beta under test from the kit's manifest; of a synthetic record, the
controller ``synthetic.record_controller_config`` makes records with (or the caller's).
``closed_loop_check`` runs the nominal and the extended model on every record and returns the
per-run figures and the closed-loop gap before and after (``gap``), which ``verdict`` judges
(``MAX_LIFT_OFF_GAP_S``).
"""

from __future__ import annotations

import csv
import math
import os
import pickle
from pathlib import Path

import numpy as np

from krang_adrc_controller.metrics import BalancingRun, physical_metrics, run_from_record
from krang_model.robot import load_krang
from krang_sim.closed_loop import ClosedLoop

from .nominal import NominalModel
from .synthetic import record_controller_config
from .workers import Workers

#: a commanded current above this (A, either wheel) is the stand command: sitting, the 2018
#: ground PD commands under 0.1 A
COMMAND_A = 1.0
#: the pitch has left the caster when it is this far above the sitting pitch, rad: 40x the
#: sitting pitch's noise on the Table II logs, a tenth of a stand-up's rise, at the top of the
#: 0.013-0.024 rad the low-current logs (beta_16/32) hover at before they leave for good
LIFT_RAD = 0.02
#: the robot stands up when its pitch rises this far above the sitting pitch, rad: about half of
#: the 0.19-0.24 rad between the Table II pose's sitting and resting pitch
STAND_RISE_RAD = 0.1
#: the stand-up current is the mean commanded current over this long before lift-off, s
STAND_CURRENT_S = 0.3
#: at rest the body balances (upright: its resting pitch between the sitting pitch +
#: STAND_RISE_RAD and + FALLEN_RAD; the Table II pose rests 0.19-0.24 rad above sitting, and a body
#: this far past it has fallen forward) with the wheels nearly still (mean |wheel speed| below
#: REST_SPEED_RAD_S over the rest interval; the logs rest at 0.02-0.1 rad/s)
FALLEN_RAD = 0.5
REST_SPEED_RAD_S = 0.5
#: the logs' controller: the mean period of the 2018 logs is 33.3 ms; the closed loop needs a whole
#: number of 1 ms physics steps, so 33 ms
HARDWARE_RATE_HZ = 1000.0 / 33.0
#: the paper-era stand PD (the kit's gains.txt), held for the whole run as in the 2018 runs;
#: neither our stops, our stand-up's caster catch nor our balance-point observer (the 2018 code
#: had none)
HARDWARE_2018 = {
    'rate_hz': HARDWARE_RATE_HZ,
    'detector.rate_hz': HARDWARE_RATE_HZ,
    'modes.stand_gains': (250.0, 40.0, 4.0, 10.0, 0.0, 0.0),
    'modes.stand_settle_s': 1e9,
    'modes.stand_tries': 0,
    'safety.stand_timeout_s': 0.0,
    'safety.max_speed_m_s': 0.0,
    'safety.fall_angle_rad': 0.0,
    'balance_point.enabled': False,
}
#: the record kinds whose controller the check knows (``controller_for``)
KNOWN_CONTROLLERS = ('hardware_csv', 'sim')
#: the stand command of a simulated run comes after this long sitting, s
SIT_S = 1.0
#: simulated time after the stand command, at most (s): the metrics' 55 s window plus a margin
MAX_AFTER_S = 57.0


def hardware_2018_config(overrides: dict | None = None):
    """The controller of the 2018 Table II runs (``HARDWARE_2018``), then `overrides`."""
    return record_controller_config({**HARDWARE_2018, **(overrides or {})})


def kit_beta(record, robot):
    """The beta under test of a kit hardware log (the manifest's beta file and row), or None."""
    src = Path(record.source or '')
    for root in src.parents:
        manifest = root / 'balancing_runs_manifest.csv'
        if manifest.exists():
            break
    else:
        return None
    rel = src.relative_to(root).as_posix()
    with open(manifest, newline='') as f:
        row = next((r for r in csv.DictReader(f) if r['file'] == rel), None)
    if row is None or not row.get('beta_file'):
        return None
    beta = np.loadtxt(root / 'betas' / row['beta_file'], ndmin=2)[int(row['beta_row_0based'])]
    return beta if beta.size == robot.nominal_beta.size else None


def run_of_record(rec) -> BalancingRun:
    """The record as a BalancingRun: commanded currents (nominal Kt x gear), the ground-referenced
    wheel angle and speed, the pitch rate (so the powers use the wheels' speed relative to the
    body)."""
    run = run_from_record(rec)
    run.dtheta_rad_s = np.asarray(rec.pitch_rate, float)
    return run


def _crossing(t, q, level, k):
    """The time q crosses `level` upwards between samples k-1 and k (linear), or t[k]."""
    if k == 0 or q[k] == q[k - 1]:
        return float(t[k])
    f = (level - q[k - 1]) / (q[k] - q[k - 1])
    return float(t[k - 1] + f * (t[k] - t[k - 1]))


def stand_metrics(run: BalancingRun, drive) -> dict:
    """What the robot of `run` did (module docstring): stand command, lift-off and stand-up times
    (s after the command; None if it never happened), sitting and resting pitch, the stand-up
    current, and ``physical_metrics`` (settle time, resting displacement, powers)."""
    t, q = run.t, run.q_base_rad
    i = np.maximum(np.abs(run.i_left), np.abs(run.i_right))
    on = np.flatnonzero(i > COMMAND_A)
    out = {
        'stand_command_s': None,
        'lift_off_s': None,
        'stand_s': None,
        'stood_up': False,
        'balanced': False,
    }
    if on.size == 0:
        return out
    k0 = int(on[0])
    t0 = float(t[k0])
    before = (t < t0) & (t >= t0 - 2.0)
    q_sit = float(np.median(q[before])) if before.any() else float(q[k0])
    out.update(stand_command_s=t0, sitting_pitch_rad=q_sit)
    rise = np.flatnonzero((q >= q_sit + STAND_RISE_RAD) & (t >= t0))
    if rise.size:
        kr = int(rise[0])
        low = np.flatnonzero(q[k0:kr] < q_sit + LIFT_RAD)
        kl = k0 + (int(low[-1]) + 1 if low.size else 0)
        lift = _crossing(t, q, q_sit + LIFT_RAD, kl)
        out.update(
            lift_off_s=max(lift - t0, 0.0),
            stand_s=_crossing(t, q, q_sit + STAND_RISE_RAD, kr) - t0,
            stood_up=True,
        )
        m = (t >= max(t0, lift - STAND_CURRENT_S)) & (t <= lift)
        if m.any():
            out['stand_current_a'] = float(np.mean(np.abs(run.i_left[m])))
    try:
        phys = physical_metrics(run, drive)
    except ValueError:
        return out
    rel = t - phys['motion_start_s']
    rest = (rel >= 20.0) & (rel <= 55.0)
    out['resting_pitch_rad'] = float(np.median(q[rest])) if rest.any() else None
    out['balanced'] = bool(
        out['stood_up']
        and rest.any()
        and q_sit + STAND_RISE_RAD <= out['resting_pitch_rad'] <= q_sit + FALLEN_RAD
        and float(np.mean(np.abs(run.dx_wheel_rad_s[rest]))) < REST_SPEED_RAD_S
    )
    for k in (
        'settle_time_s',
        'resting_displacement_m',
        'max_displacement_m',
        'peak_electrical_power_w',
        'peak_mechanical_power_w',
        'mean_resting_electrical_power_w',
        'mean_resting_mechanical_power_w',
    ):
        v = phys[k]
        out[k] = None if v is None or not math.isfinite(v) else float(v)
    out['window_s'] = phys['window_s']
    return out


def controller_for(record, model, controller_config=None, controller_beta=None):
    """(ControllerConfig, beta) the run was made with: given, or by the record's kind (module
    docstring). A kit log whose beta the manifest does not give runs with the model's beta."""
    if record.kind == 'hardware_csv':
        cfg = controller_config or hardware_2018_config()
        beta = controller_beta if controller_beta is not None else kit_beta(record, model.robot)
    else:
        rate = record.meta.get('controller_rate_hz')
        cfg = controller_config or record_controller_config(
            {'rate_hz': rate, 'detector.rate_hz': min(rate, 50.0)} if rate else None
        )
        beta = controller_beta
    return cfg, (model.beta if beta is None else np.asarray(beta, float))


def simulate_run(record, model, terms, *, controller_config=None, controller_beta=None, seed=0):
    """The closed-loop replay of `record` on the reduced plant with the model's `terms`: sit in
    the record's pose (its median joints before the stand command) for ``SIT_S``, enable (the
    controller stands up at once), run as long after it as the record does (at most
    ``MAX_AFTER_S``). Returns (BalancingRun logged at the record's rate, stand_metrics)."""
    cfg, beta = controller_for(record, model, controller_config, controller_beta)
    meas = run_of_record(record)
    m = stand_metrics(meas, model.drive)
    t0 = m['stand_command_s'] if m['stand_command_s'] is not None else float(record.t[0])
    sit = (record.t < t0) & (record.t >= t0 - 2.0)
    pose = np.median(record.joints[sit] if sit.any() else record.joints[:1], axis=0)
    after = min(float(record.t[-1]) - t0, MAX_AFTER_S)
    loop = ClosedLoop(
        model.robot,
        model.beta,
        beta,
        pose,
        controller_config=cfg,
        plant='reduced',
        terms=terms,
        seed=seed,
        log_rate_hz=1.0 / record.period,
    )
    loop.run(SIT_S)
    loop.controller.set_enabled(True)
    loop.run(max(after, 1.0))
    run = loop.balancing_run(name=record.name)
    sim = BalancingRun(
        t=run.t,
        i_left=run.i_left,
        i_right=run.i_right,
        x_wheel_rad=run.x_wheel_rad,
        dx_wheel_rad_s=run.dx_wheel_rad_s,
        dtheta_rad_s=run.dtheta_rad_s,
        q_base_rad=run.q_base_rad,
        name=record.name,
    )
    return sim, stand_metrics(sim, model.drive)


def _simulate_job(job):
    """``simulate_run`` in a worker process: (record, robot or None for ``load_krang()``, beta,
    drive, terms, controller config, controller beta, seed)."""
    rec, robot, beta, drive, terms, cfg, ctl_beta, seed = job
    model = NominalModel(robot if robot is not None else load_krang(), beta, drive)
    return simulate_run(
        rec, model, terms, controller_config=cfg, controller_beta=ctl_beta, seed=seed
    )


#: the replays go to worker processes when the records give at least this much simulated time
#: (s, the nominal and the extended model together): about twice what a worker costs to start
WORKER_MIN_S = 240.0


class ClosedLoopRuns:
    """The closed-loop replays of ``closed_loop_check``, started as soon as a model is known
    (``submit``) and collected when needed (``results``). Each replay is one Python loop of
    1 ms physics steps, about a second of CPU for a Table II run, and independent of every other:
    with `workers` > 1 and at least `min_replayed_s` to simulate they run in that many worker
    interpreters (``workers.Workers``, about 200 MB each) beside the fits of the calling process,
    so that ``run_discrepancy`` starts the nominal model's replays before it names anything. The
    results are the in-process ones (the same code and seeds); a model that cannot be pickled (an
    effect with a Python formula) replays in-process, and so does any replay whose worker
    failed."""

    def __init__(
        self,
        records,
        model,
        *,
        controller_config=None,
        controller_beta=None,
        seed=0,
        workers=1,
        min_replayed_s=WORKER_MIN_S,
    ):
        self.records = [
            r for r in records if controller_config is not None or r.kind in KNOWN_CONTROLLERS
        ]
        self.model = model
        self._opts = (controller_config, controller_beta, seed)
        # a worker costs about 2 s of CPU to start, a replay about 1 s per minute simulated
        replayed = 2.0 * sum(min(r.duration, MAX_AFTER_S) for r in self.records)
        self.parallel = int(workers) > 1 and replayed >= min_replayed_s
        self.workers = max(1, min(int(workers), len(self.records)))
        self._pool = None
        self._jobs = {}  # label -> (terms, [Future or None per record])

    def submit(self, label: str, terms) -> None:
        """Start the replays of every record with the model `terms` (in the workers, when there
        are any and the model can go there)."""
        if label in self._jobs and self._jobs[label][0] is terms:
            return
        futures = [None] * len(self.records)
        if self.parallel:
            robot = None if self.model.robot is load_krang() else self.model.robot
            jobs = [
                (rec, robot, self.model.beta, self.model.drive, terms, *self._opts)
                for rec in self.records
            ]
            try:
                pickle.dumps(jobs[0])
            except Exception:  # a Python formula in the terms: replayed in-process
                jobs = None
            if jobs is not None:
                if self._pool is None:
                    self._pool = Workers(self.workers)
                futures = [self._pool.submit(_simulate_job, j) for j in jobs]
        self._jobs[label] = (terms, futures)

    def results(self, label: str, terms) -> list:
        """[(BalancingRun, stand_metrics)] per record for the model `terms` (submitted now if it
        was not, under this label)."""
        self.submit(label, terms)
        cfg, ctl_beta, seed = self._opts
        out = []
        for rec, fut in zip(self.records, self._jobs[label][1]):
            if fut is not None:
                try:
                    out.append(fut.result())
                    continue
                except Exception:  # a worker that failed: the replay runs here instead
                    pass
            out.append(
                simulate_run(
                    rec,
                    self.model,
                    terms,
                    controller_config=cfg,
                    controller_beta=ctl_beta,
                    seed=seed,
                )
            )
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None


def default_workers() -> int:
    """Processes for the closed-loop replays: the machine's cores, at most 4."""
    return min(4, os.cpu_count() or 1)


#: the figures the closed-loop gap compares, measured against simulated
GAP_KEYS = (
    'lift_off_s',
    'settle_time_s',
    'resting_displacement_m',
    'resting_pitch_rad',
    'peak_electrical_power_w',
    'mean_resting_electrical_power_w',
)


def _gap(measured: list, simulated: list) -> dict:
    """Per figure: median |simulated - measured| over the runs where both have it; the worst
    |lift-off error|; the runs where the real robot stood up (or came to rest balanced) and the
    simulated one did not (``missed_stand_up``)."""
    out = {}
    for k in GAP_KEYS:
        d = [
            abs(s[k] - m[k])
            for m, s in zip(measured, simulated)
            if m.get(k) is not None and s.get(k) is not None
        ]
        out[k] = float(np.median(d)) if d else None
    both = [
        (m['lift_off_s'], s['lift_off_s'])
        for m, s in zip(measured, simulated)
        if m['stood_up'] and s['stood_up']
    ]
    out['lift_off_worst_s'] = max((abs(b - a) for a, b in both), default=None)
    out['runs'] = len(measured)
    out['stood_up'] = sum(bool(s['stood_up']) for s in simulated)
    out['balanced'] = sum(bool(s['balanced']) for s in simulated)
    out['measured_stood_up'] = sum(bool(m['stood_up']) for m in measured)
    out['measured_balanced'] = sum(bool(m['balanced']) for m in measured)
    out['missed_stand_up'] = sum(
        (m['stood_up'] and not s['stood_up']) or (m['balanced'] and not s['balanced'])
        for m, s in zip(measured, simulated)
    )
    return out


def closed_loop_check(
    records,
    model,
    before,
    after,
    *,
    controller_config=None,
    controller_beta=None,
    seed=0,
    keep_traces=True,
    others=None,
    runs: ClosedLoopRuns | None = None,
) -> dict:
    """Replay every record in closed loop with the `before` (nominal) and `after` (extended)
    ``ModelTerms``; records whose controller is unknown (not in ``KNOWN_CONTROLLERS``, no
    `controller_config`) are left out. `others`: more models, {label: ModelTerms}, replayed
    alike (candidates). Returns {'runs': [{name, measured, before, after, label...}], 'gap':
    {'before', 'after', label...} (``_gap``), 'traces': {name: {'measured'|'before'|'after'|label:
    (t - stand command, q_base)}}, 'definitions'}; 'lift_off_gap_s' [before, after]: the lift-off
    figure the verdict reads (``lift_off_gap``). `runs`: the replays, some perhaps started
    already (``ClosedLoopRuns`` of the same records, model and options; default: in-process)."""
    if runs is None:
        runs = ClosedLoopRuns(
            records,
            model,
            controller_config=controller_config,
            controller_beta=controller_beta,
            seed=seed,
        )
    models = {'before': before, 'after': after, **(others or {})}
    for key, terms in models.items():
        runs.submit(key, terms)
    done = {key: runs.results(key, terms) for key, terms in models.items()}
    entries, traces = [], {}
    meas_all, sims = [], {k: [] for k in models}
    for i, rec in enumerate(runs.records):
        meas_run = run_of_record(rec)
        meas = stand_metrics(meas_run, model.drive)
        entry = {'name': rec.name, 'measured': meas}
        tr = {'measured': _trace(meas_run, meas)}
        for key in models:
            sim_run, sim = done[key][i]
            entry[key] = sim
            sims[key].append(sim)
            tr[key] = _trace(sim_run, sim)
        entries.append(entry)
        meas_all.append(meas)
        if keep_traces:
            traces[rec.name] = tr
    gap = {k: _gap(meas_all, sims[k]) for k in models}
    return {
        'runs': entries,
        'gap': gap,
        'lift_off_gap_s': [lift_off_gap(gap['before']), lift_off_gap(gap['after'])],
        'traces': traces,
        'lift_rad': LIFT_RAD,
        'definitions': {
            'stand_command': f'first sample with a commanded current above {COMMAND_A:g} A',
            'lift_off_s': f'time after the stand command at which the pitch leaves the caster '
            f'for good (sitting pitch + {LIFT_RAD:g} rad, last crossing before it rises '
            f'{STAND_RISE_RAD:g} rad)',
            'settle_time_s': 'time since motion start after which the wheel position stays '
            'within 8 cm of its rest (20-55 s mean)',
            'power': 'commanded currents x nominal Kt x gear, both wheels; electrical = '
            'R i^2 + tau w, mechanical |tau w| (wheel speed relative to the body), W',
            'gap': 'median |simulated - measured| over the runs; lift_off_worst_s: the largest '
            '|lift-off error|; missed_stand_up: runs where the real robot lifted off (or came to '
            'rest balanced: resting pitch 0.1-0.5 rad above sitting, wheels nearly still) and '
            'the simulated one did not',
        },
    }


def closed_loop_json(closed: dict) -> dict:
    """The check for the ``--json`` object: without the traces; an infinite lift-off gap (a
    lift-off missed) is None there, the counts say why."""
    return {
        'runs': closed['runs'],
        'gap': closed['gap'],
        'lift_off_gap_s': [None if not math.isfinite(g) else g for g in closed['lift_off_gap_s']],
        'definitions': closed['definitions'],
    }


def lift_off_gap(gap: dict) -> float:
    """The lift-off gap of one model (s): inf when it misses a stand-up the logs show (no
    lift-off, or no rest balanced where the real robot came to rest), else the worst |lift-off
    error| over the runs (nan when no run lifted off at all)."""
    if gap['missed_stand_up']:
        return math.inf
    v = gap['lift_off_worst_s']
    return math.nan if v is None else float(v)


def _trace(run, m):
    t0 = m['stand_command_s'] if m['stand_command_s'] is not None else float(run.t[0])
    return (run.t - t0, run.q_base_rad)


# ------------------------------------------------------------------ candidates the check can try


def with_caster_friction(terms, mu: float, speed_rad_s: float = 0.01):
    """`terms` plus dry friction at the caster's floor contact, coefficient `mu`: a horizontal
    force mu N opposing the contact point's motion, N the caster's normal load (its penalty torque
    on the body over the contact's horizontal lever arm). The contact sits one wheel radius below
    the axle, fixed in the body, so it moves at r (phi' - q_base'): the generalised forces are
    -+ mu N r tanh(.) on the wheel and pitch equations, a torque between wheel and body like the
    wheels' own Coulomb friction, but only while the body rests on the caster (zero at lift-off).
    A candidate of the closed-loop check (an extra force: the reduced plant only)."""
    d = terms.drive
    cp, k, c = d.caster_contact_pitch, d.caster_stiffness, d.caster_damping
    lever = math.sqrt(d.caster_distance**2 - (d.wheel_radius - d.caster_radius) ** 2)
    gain = mu * d.wheel_radius / lever

    def force(s):
        pen = cp - s.q_base
        if pen <= 0.0:
            return 0.0, 0.0
        f = (
            gain
            * max(k * pen - c * s.dq_base, 0.0)
            * math.tanh((s.dphi - s.dq_base) / speed_rad_s)
        )
        return -f, f

    out = terms.copy()
    out.extra_forces.append(force)
    return out


def candidate_terms(model, spec: str):
    """A candidate model from 'key=value,key=value' (effects of ``krang_model.effects``, the
    optional ones included, applied in order on the nominal model; ``caster_friction=MU`` adds
    ``with_caster_friction``)."""
    from krang_model.effects import model_terms, register_optional_effects

    register_optional_effects()
    pairs = [p.split('=') for p in spec.split(',') if p]
    mu = [float(v) for k, v in pairs if k == 'caster_friction']
    terms = model_terms([(k, float(v)) for k, v in pairs if k != 'caster_friction'], model.terms())
    return with_caster_friction(terms, mu[0]) if mu else terms


def main(argv=None) -> int:
    """``python -m krang_discrepancy.closed_loop_check --measured FILES --model EXT.yaml --out
    DIR [--candidate LABEL:key=v,key=v ...]``: the check on its own (DIR/closed_loop.json,
    DIR/closed_loop.png), with candidate models beside the nominal and the extended one."""
    import argparse
    import json

    from .extended_model import load_extended_model, plain
    from .figures import plot_closed_loop
    from .loaders import load_measured
    from .nominal import NominalModel

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument('--measured', nargs='+', required=True)
    ap.add_argument('--model', required=True, help='extended_model.yaml (the "after" model)')
    ap.add_argument('--candidate', action='append', default=[], help='LABEL:key=v,key=v')
    ap.add_argument('--figure-runs', nargs='*', default=None, help='runs to draw')
    ap.add_argument(
        '--one-step', action='store_true', help="each model's one-step gap too (stride 0.1 s)"
    )
    ap.add_argument('--out', required=True)
    args = ap.parse_args(argv)
    model = NominalModel.default()
    records = load_measured(args.measured)
    others = {}
    for c in args.candidate:
        label, _, spec = c.partition(':')
        others[label] = candidate_terms(model, spec)
    closed = closed_loop_check(
        records,
        model,
        model.terms(),
        load_extended_model(args.model, model.terms()),
        others=others,
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'closed_loop.json').write_text(json.dumps(plain(closed_loop_json(closed)), indent=1))
    plot_closed_loop(closed, out, names=args.figure_runs)
    if args.one_step:
        from .replay import Replay, ReplayConfig, gap_metrics

        replay = Replay(records, model, ReplayConfig(stride_s=0.1))
        replay.set_scales(replay.residuals([model.terms()])[0])
        ext = load_extended_model(args.model, model.terms())
        for label, terms in {'before': model.terms(), 'after': ext, **others}.items():
            g = gap_metrics(replay, replay.residuals([terms])[0])
            print(f'{label}: one-step gap {g["gap"]:.3f} (pitch {g["rms_q_base"]:.4f} rad)')
    for label, g in closed['gap'].items():
        print(
            f'{label}: stood up {g["stood_up"]}/{g["runs"]} (measured {g["measured_stood_up"]}), '
            f'balanced {g["balanced"]} (measured {g["measured_balanced"]}), missed stand-ups '
            f'{g["missed_stand_up"]}, |lift-off error| median {g["lift_off_s"]} s, worst '
            f'{g["lift_off_worst_s"]} s; median |settle time error| {g["settle_time_s"]} s'
        )
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
