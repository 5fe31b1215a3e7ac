"""The multiple-shooting replay: the nominal (or extended) model driven by the measured initial
states, commands and poses, for many parameter sets at once.

Why short horizons (multiple shooting) and not one long rollout
    The balancing robot is an open-loop unstable pendulum (pole near +5 rad/s for the Table II
    pose). An open-loop rollout from the first sample with the measured commands diverges from any
    tiny error within a second or two, whatever the model, so its "gap" measures the instability,
    the initial condition, not the missing physics. A closed-loop re-simulation with our controller
    would not be the hardware's controller, and feedback hides the effects it compensates. So the
    replay starts a short prediction (default 0.3 s, about 1.5 time constants) at every measured
    state (every ``stride_s``), drives it with the measured commands and the measured pose, and
    compares the predicted signals with the measured ones along the horizon. Errors cannot compound
    across windows; a missing effect shows up as a systematic prediction error.

The model is ``krang_model.wip``'s one statement of the equations and its one integrator,
compiled over the batch (``krang_model.wip_batch.integrate``): all windows and all parameter sets
of a fit step at once, in chunks on a few threads. The effects are those of
``krang_model.effects`` (``ModelTerms``); the commands reach the model as the drives apply them
(``krang_model.drivetrain.HeldCommand``: held, delayed by the actuation delay). Poses are reduced
with ``krang_model.wip.reduce_placements`` and payloads added with ``point_mass_beta``, as the
plant does.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from krang_model.drivetrain import HeldCommand
from krang_model.effects import ModelTerms
from krang_model.kinematics import body_placements
from krang_model.wip import point_mass_beta, reduce_placements
from krang_model.wip_batch import drive_table, integrate

from .nominal import NominalModel
from .phases import PHASES, label_phases
from .record import CHANNELS, Record


@dataclass
class ReplayConfig:
    horizon_s: float = 0.3  # prediction horizon of each window
    stride_s: float = 0.05  # a window starts every stride
    n_eval: int = 3  # comparison points along the horizon (equally spaced, last = H)
    substep_s: float = 0.002  # largest integration step
    smooth_s: float = 0.02  # half-width of the gyro-aided smoothing of the measured pitch
    body_period_s: float = 0.02  # pose reduction period while joints move
    pose_delay_s: float = 0.0  # the body follows the measured joints this much later
    caster_margin: float = 0.02  # windows that come this close to the caster pitch are 'sitting'
    max_windows: int = 4000  # per record (stride is widened beyond)
    # over all records: the stride widens, for all of them alike, until they hold at most this
    # many windows (0: no limit). 20 000 takes 30 min of 30 Hz logs (the Table II baseline) at a
    # stride of 0.1 s, where every instant is still in three windows (docs/discrepancy.md §8)
    max_total_windows: int = 20_000
    workers: int = 0  # threads of the prediction (0: the machine's cores, at most 4)


@dataclass
class _Rec:
    """Per-record precomputations."""

    record: Record
    labels: np.ndarray
    tb: np.ndarray  # body-table times
    jb: np.ndarray  # body-table joints (K, 16)
    ct: np.ndarray  # (M,) command times
    lr: np.ndarray  # (M, 2) per-wheel commanded torques (N m)


class Replay:
    """Multiple-shooting replay of records under the nominal model or any extension of it.

    ``predict(terms_list)`` -> predicted measurements (P, S, E, 4) for P parameter sets, S windows,
    E points along the horizon, channels CHANNELS; ``measured`` is (S, E, 4); ``residuals`` the
    difference. Window metadata: ``win_record``, ``win_t`` (start time), ``win_phase``.
    """

    def __init__(
        self, records, model: NominalModel, config: ReplayConfig | None = None, phases=None
    ):
        self.model = model
        self.cfg = cfg = config or ReplayConfig()
        self.records = list(records) if isinstance(records, (list, tuple)) else [records]
        d = model.drive
        self._recs = []
        starts, t_start, rec_id, phase, inits, meas = [], [], [], [], [], []
        self._h = None
        strides = self._strides()
        for ri, rec in enumerate(self.records):
            h, n_steps, step_samples, eval_samples = self._grid(rec.period)
            if self._h is None:
                self._h, self._n_steps = h, n_steps
                self._horizon = n_steps * h
                self.eval_steps = np.round(eval_samples / step_samples).astype(int)
            elif abs(h - self._h) > 1e-6 * self._h or n_steps != self._n_steps:
                raise ValueError(
                    'records with different sample periods: resample them to one rate '
                    f'({rec.name}: {rec.period:.4g} s vs {self.records[0].period:.4g} s)'
                )
            n_h = int(eval_samples[-1])
            eval_off = eval_samples
            labels = label_phases(rec, d.caster_pitch)
            ks = np.arange(0, len(rec) - n_h, strides[ri])
            if ks.size > cfg.max_windows:
                ks = ks[np.linspace(0, ks.size - 1, cfg.max_windows).astype(int)]
            eval_off = np.round(np.linspace(n_h / cfg.n_eval, n_h, cfg.n_eval)).astype(int)
            qs = self._smooth_pitch(rec)
            sig = np.column_stack([qs, rec.pitch_rate, rec.wheel, rec.wheel_rate])
            # windows touching the caster are 'sitting' whatever the label at their start
            win_min = (
                np.array([rec.q_base[k : k + n_h + 1].min() for k in ks])
                if ks.size
                else np.zeros(0)
            )
            ph = labels[ks].copy()
            ph[win_min < d.caster_pitch + cfg.caster_margin] = 'sitting'
            ok = np.all(np.isfinite(sig[ks]), axis=1)
            for e in eval_off:
                ok &= np.all(np.isfinite(sig[ks + e]), axis=1)
            ks, ph = ks[ok], ph[ok]
            starts.append(ks)
            t_start.append(rec.t[ks])
            rec_id.append(np.full(ks.size, ri))
            phase.append(ph)
            inits.append(sig[ks])
            meas.append(np.stack([sig[ks + e] for e in eval_off], axis=1))
            tb, jb = self._body_samples(rec)
            lr = rec.cmd_torque if rec.cmd_t.size else np.zeros((0, 2))
            self._recs.append(_Rec(rec, labels, tb, jb, rec.cmd_t, lr))
        self.win_k = np.concatenate(starts)
        self.win_t = np.concatenate(t_start)
        self.win_record = np.concatenate(rec_id)
        self.win_phase = np.concatenate(phase)
        self.init = np.concatenate(inits)  # (S, 4) measured state at the start
        self.measured = np.concatenate(meas)  # (S, E, 4)
        self.eval_tau = self.eval_steps * self._h
        # sub-step times (S, J+1) and body-table interpolation
        self.sub_t = self.win_t[:, None] + self._h * np.arange(self._n_steps + 1)[None]
        self._body_cache = {}
        self._reduce_cache = {}
        self._torque_cache = {}
        self._held_cache = {}
        self.select(phases)
        self.scales = None
        self.timing = {}
        self.trig_anchor = 16  # exact sines and cosines every this many sub-steps (wip_batch)
        self.workers = cfg.workers or min(4, os.cpu_count() or 1)

    # ------------------------------------------------------------------ set-up helpers
    @property
    def horizon(self) -> float:
        return self._horizon

    @property
    def substep(self) -> float:
        return self._h

    def __len__(self):
        return self.win_t.size

    def select(self, phases=None):
        """Restrict ``active`` (the windows fits use) to these phases (None: all of them). The
        sitting windows are evidence too: the pitch on the caster is fixed by the caster geometry,
        the wheel radius, the floor slope and the IMU bias, with no model of the body or drives."""
        if phases is None:
            phases = PHASES
        self.phases = tuple(phases)
        self.active = np.isin(self.win_phase, self.phases)
        return self.active

    def _strides(self):
        """Samples between window starts, per record: ``stride_s``, widened alike for every
        record until they hold at most ``max_total_windows`` windows (each record's counted up to
        ``max_windows``, where it is thinned anyway). ``stride_s`` (the attribute) is the stride
        in seconds the windows start at."""
        cfg = self.cfg

        def windows(stride_s, to_int):
            ks = [max(1, to_int(stride_s / r.period)) for r in self.records]
            ends = [len(r) - int(self._grid(r.period)[3][-1]) for r in self.records]
            return ks, sum(min(len(range(0, e, k)), cfg.max_windows) for e, k in zip(ends, ks))

        ks, total = windows(cfg.stride_s, lambda x: int(round(x)))
        self.unwidened_windows = total
        self.stride_s = cfg.stride_s
        while cfg.max_total_windows and total > cfg.max_total_windows:
            # from the stride the samples give (a whole number of them) to one that fits
            wider = max(k * r.period for k, r in zip(ks, self.records))
            wider *= total / cfg.max_total_windows
            ks, total = windows(wider, lambda x: int(math.ceil(x - 1e-9)))
            self.stride_s = max(k * r.period for k, r in zip(ks, self.records))
        return ks

    def widened(self) -> str:
        """Why the windows start farther apart than ``stride_s`` asked ('' if they do not)."""
        cfg = self.cfg
        if self.stride_s <= cfg.stride_s * (1 + 1e-9):
            return ''
        return (
            f'{self.unwidened_windows} windows at a stride of {cfg.stride_s:g} s exceed the '
            f'budget of {cfg.max_total_windows} (--max-windows): a window every '
            f'{self.stride_s:.3g} s, {len(self)} windows'
        )

    def _grid(self, period):
        """(sub-step h, steps per horizon, samples per step, eval offsets in samples) for a
        measurement period: h divides the period (slow data) or is a multiple of it (fast data),
        and every comparison point falls on both a sample and a sub-step boundary."""
        cfg = self.cfg
        if period >= cfg.substep_s:
            m = int(math.ceil(period / cfg.substep_s - 1e-9))
            n_h = max(cfg.n_eval, int(round(cfg.horizon_s / period)))
            ev = np.round(np.linspace(n_h / cfg.n_eval, n_h, cfg.n_eval)).astype(int)
            return period / m, n_h * m, 1.0 / m, ev
        q = max(1, int(math.floor(cfg.substep_s / period + 1e-9)))
        n_steps = max(cfg.n_eval, int(round(cfg.horizon_s / (q * period))))
        ev_steps = np.round(np.linspace(n_steps / cfg.n_eval, n_steps, cfg.n_eval)).astype(int)
        return q * period, n_steps, float(q), ev_steps * q

    def _smooth_pitch(self, rec):
        """Gyro-aided moving average of the IMU pitch: mean over +-smooth_s of
        (q_base_j - integral of the rate from t_k to t_j). Unbiased for any pitch motion when the
        rate is right; it only averages the angle noise."""
        w = int(round(self.cfg.smooth_s / rec.period))
        if w < 1:
            return rec.q_base.copy()
        a = np.concatenate(
            [[0.0], np.cumsum(0.5 * (rec.pitch_rate[1:] + rec.pitch_rate[:-1]) * np.diff(rec.t))]
        )
        d = rec.q_base - a
        kern = np.ones(2 * w + 1)
        num = np.convolve(d, kern, mode='same')
        cnt = np.convolve(np.ones_like(d), kern, mode='same')
        return num / cnt + a

    def _body_samples(self, rec):
        """Times and joints (bin means over body_period_s) at which the pose is reduced; bins
        inside still stretches are dropped (linear interpolation between the kept ones is exact
        there), so a record that mostly holds its pose needs few reductions."""
        span = np.ptp(rec.joints, axis=0).max()
        delay = self.cfg.pose_delay_s
        if span < 2e-3:
            return np.array([rec.t[0]]), rec.joints.mean(axis=0, keepdims=True)
        per = max(1, int(round(self.cfg.body_period_s / rec.period)))
        n = len(rec) // per
        jb = rec.joints[: n * per].reshape(n, per, -1).mean(axis=1)
        tb = rec.t[: n * per].reshape(n, per).mean(axis=1) + delay
        keep = [0]
        tol = 5e-4
        for i in range(1, n):
            if np.max(np.abs(jb[i] - jb[keep[-1]])) > tol:
                if keep[-1] != i - 1:
                    keep.append(i - 1)
                keep.append(i)
        if keep[-1] != n - 1:
            keep.append(n - 1)
        keep = np.array(keep)
        return tb[keep], jb[keep]

    def _placements(self, offsets_key):
        """Per record: the body placements at the body-table joints shifted by the encoder offsets
        (cached by offsets): payload variants then cost only the mass contraction."""
        hit = _lru_get(self._reduce_cache, offsets_key)
        if hit is not None:
            return hit
        robot = self.model.robot
        out = []
        for r in self._recs:
            joints = r.jb.copy()
            for jname, off in offsets_key:
                joints[:, robot.pose_joints.index(jname)] -= off  # true = measured - offset
            out.append(body_placements(robot, joints))
        _lru_put(self._reduce_cache, offsets_key, out, 64)
        return out

    def _body_arrays(self, terms: ModelTerms):
        """(mass, com distance (S,J), offset (S,J), inertia (S,J)) of this body variant at the
        mid-point of every sub-step (cached by terms.body_key()). A payload is added to its link's
        beta (krang_model.wip.point_mass_beta) and the pose reduced again, as in the simulator."""
        key = terms.body_key()
        hit = _lru_get(self._body_cache, key)
        if hit is not None:
            return hit
        robot, beta = self.model.robot, self.model.beta
        for link, point, kg in terms.payloads:
            beta = point_mass_beta(robot, beta, link, point, kg)
        places = self._placements(key[1])
        still = all(len(r.tb) == 1 for r in self._recs)
        # a record whose pose never moves needs one value per window, broadcast over sub-steps
        mid = self.sub_t[:, :1] if still else 0.5 * (self.sub_t[:, 1:] + self.sub_t[:, :-1])
        out = [np.empty(mid.shape) for _ in range(3)]
        mass = 0.0
        for ri, r in enumerate(self._recs):
            sel = self.win_record == ri
            if not np.any(sel):
                continue
            body = reduce_placements(robot, *places[ri], beta)
            mass = float(body.mass[0])
            tq = mid[sel]
            for k, v in enumerate((body.com_distance, body.com_offset, body.inertia_axle)):
                out[k][sel] = v[0] if v.size == 1 else np.interp(tq, r.tb, v)
        out = (mass, *out)
        _lru_put(self._body_cache, key, out, 24, CACHE_BYTES)
        return out

    def _held_torque(self, ri: int, lim: float) -> HeldCommand:
        """Record ri's commanded total wheel torque as the drives apply it, the per-wheel commands
        clamped at `lim` (N m) (cached per clamp)."""
        key = (ri, lim)
        hit = self._held_cache.get(key)
        if hit is None:
            r = self._recs[ri]
            hit = HeldCommand(r.ct, np.clip(r.lr, -lim, lim).sum(axis=1))
            self._held_cache[key] = hit
        return hit

    def _torque_arrays(self, delay: float, current_limit: float):
        """Average applied total torque over each sub-step (S, J): the commands delayed by
        `delay` (``HeldCommand``), the per-wheel commands clamped at the record's torque limit or
        at `current_limit` (A) of the nominal motors, whichever is lower."""
        key = (delay, current_limit)
        hit = _lru_get(self._torque_cache, key)
        if hit is not None:
            return hit
        k_motor = self.model.drive.torque_constant * self.model.drive.gear_ratio
        tq = np.empty((self.sub_t.shape[0], self._n_steps))
        for ri, r in enumerate(self._recs):
            sel = self.win_record == ri
            if not np.any(sel):
                continue
            lim = min(current_limit * k_motor, r.record.torque_limit)
            c = self._held_torque(ri, lim).integral(self.sub_t[sel], delay)
            tq[sel] = np.diff(c, axis=1) / self._h
        _lru_put(self._torque_cache, key, tq, 12, CACHE_BYTES)
        return tq

    # ------------------------------------------------------------------ prediction
    def predict(self, terms_list, windows=None, trajectory=False, max_elements: int = 32_000):
        """Predicted measurements (P, S, E, 4) for each ModelTerms in `terms_list` (windows: an
        index/mask into the windows, default all). With trajectory=True also returns the sub-step
        states (P, S, J+1, 4) as measured channels.

        All P parameter sets step together; body variants (payloads, encoder offsets) and delays
        are computed once per distinct value and gathered per element. The windows go in chunks
        that keep (parameter sets x windows) below `max_elements`, whose tables of body and
        torque per sub-step stay in the processor's cache. The chunks run on ``workers`` threads
        (the compiled loop releases the interpreter lock); every element's result is independent
        of the chunk and the thread it runs in. So there is at least one chunk per worker when the
        batch is large enough (a single run's windows, one parameter set)."""
        t_start = time.perf_counter()
        if isinstance(terms_list, ModelTerms):
            terms_list = [terms_list]
        # a parameter set asked for twice is predicted once (the joint fits of the consistency
        # checks start with all their jobs at the same values)
        uniq, back = unique_terms(terms_list)
        if len(uniq) < len(terms_list):
            got = self.predict(uniq, windows, trajectory, max_elements)
            return tuple(x[back] for x in got) if trajectory else got[back]
        sel = np.arange(len(self)) if windows is None else np.arange(len(self))[windows]
        prep = self._prepare(terms_list)
        p = max(1, len(terms_list))
        chunk = max(1, max_elements // p)
        if self.workers > 1 and sel.size * p >= self.workers * MIN_CHUNK_ELEMENTS:
            chunk = min(chunk, -(-sel.size // self.workers))
        parts = [sel[i : i + chunk] for i in range(0, sel.size, chunk)] or [sel]
        run = lambda s: self._predict_chunk(prep, s, trajectory)  # noqa: E731
        if len(parts) > 1 and self.workers > 1:
            results = list(_pool(self.workers).map(run, parts))
        else:
            results = [run(s) for s in parts]
        self.timing['predict_s'] = (
            self.timing.get('predict_s', 0.0) + time.perf_counter() - t_start
        )
        self.timing['predict_calls'] = self.timing.get('predict_calls', 0) + 1
        self.timing['predict_sets'] = self.timing.get('predict_sets', 0) + len(terms_list)
        PREDICTED['sets'] += len(terms_list)
        PREDICTED['calls'] += 1
        PREDICTED['element_steps'] += len(terms_list) * sel.size * self._n_steps
        join = lambda xs: xs[0] if len(xs) == 1 else np.concatenate(xs, axis=1)  # noqa: E731
        out = (
            (join([r[0] for r in results]), join([r[1] for r in results]))
            if trajectory
            else join(results)
        )
        return out

    def _prepare(self, terms_list) -> dict:
        """What the chunks of one prediction share: the distinct body variants and delayed
        torques over all windows (computed here, in the calling thread, so that the caches are
        only read by the workers) and each set's index into them and its drive train."""
        col = lambda name: np.array([float(getattr(tm, name)) for tm in terms_list])  # noqa: E731
        bkeys = [tm.body_key() for tm in terms_list]
        ukeys = list(dict.fromkeys(bkeys))
        first = {k: terms_list[bkeys.index(k)] for k in ukeys}
        bodies = [self._body_arrays(first[k]) for k in ukeys]
        delays = [(tm.actuation_delay, tm.drive.current_limit) for tm in terms_list]
        udel = list(dict.fromkeys(delays))
        nominal_kt = self.model.drive.torque_constant
        return {
            'bias': col('imu_pitch_bias'),
            'com_shift': col('com_shift'),
            'inertia_add': col('inertia_add'),
            # applied / commanded torque: the commands were computed with the nominal Kt
            't_scale': np.array([tm.drive.torque_constant / nominal_kt for tm in terms_list]),
            'drive': drive_table([tm.drive for tm in terms_list]),
            'mass': np.array([bd[0] for bd in bodies]),
            'bodies': bodies,
            'bidx': np.array([ukeys.index(k) for k in bkeys], np.int64),
            'didx': np.array([udel.index(d) for d in delays], np.int64),
            'torques': [self._torque_arrays(*d) for d in udel],
            'extra': [tm.extra_forces for tm in terms_list],
        }

    def _predict_chunk(self, prep: dict, sel, trajectory=False):
        """``predict`` on the windows `sel` (an index array): ``krang_model.wip_batch.integrate``
        over all sub-steps at once, or sub-step by sub-step where a set has extra forces (Python
        callables of the state)."""
        extra = prep['extra']
        P, S, J = len(extra), sel.size, self._n_steps
        # (variants, windows, sub-steps): each window's sub-steps in one stretch of memory
        table = lambda arrays: np.stack([a[sel] for a in arrays])  # noqa: E731
        dist, offset, inertia = (table([bd[k] for bd in prep['bodies']]) for k in (1, 2, 3))
        torque = table(prep['torques'])
        # initial state (true pitch = measured - bias)
        x0 = self.init[sel]
        state = np.empty((P, S, 4))
        state[..., 1] = x0[:, 0][None] - prep['bias'][:, None]
        state[..., 3] = x0[:, 1]
        state[..., 0] = state[..., 1] + x0[:, 2]
        state[..., 2] = state[..., 3] + x0[:, 3]
        trig = np.zeros((P, S, 2))
        steps = np.arange(J + 1) if trajectory else self.eval_steps
        slot = np.full(J + 1, -1, np.int64)
        slot[steps] = np.arange(steps.size)
        rec = np.empty((P, S, steps.size, 4))
        if trajectory:
            rec[:, :, 0] = state
        f_phi, f_qbase = np.zeros((P, S)), np.zeros((P, S))
        args = (
            *(self._h, self.trig_anchor, prep['mass'], dist, offset, inertia, prep['bidx']),
            *(torque, prep['didx'], prep['t_scale'], prep['com_shift'], prep['inertia_add']),
            prep['drive'],
        )
        if not any(extra):
            integrate(state, trig, 0, J, *args, f_phi, f_qbase, slot, rec)
        for j in range(J) if any(extra) else ():
            jb = min(j, dist.shape[2] - 1)
            for p, forces in enumerate(extra):
                u, qb = prep['bidx'][p], state[p, :, 1]
                st = _State(
                    *(state[p, :, 0], qb, state[p, :, 2], state[p, :, 3], qb + offset[u, :, jb]),
                    torque[prep['didx'][p], :, j] * prep['t_scale'][p],
                    self.sub_t[sel, j],
                )
                f_phi[p], f_qbase[p] = 0.0, 0.0
                for fn in forces:
                    a1, a2 = fn(st)
                    f_phi[p] += a1
                    f_qbase[p] += a2
            integrate(state, trig, j, j + 1, *args, f_phi, f_qbase, slot, rec)
        # measured channels: pitch (+ bias), pitch rate, wheel relative to the body, its rate
        out = np.empty_like(rec)
        out[..., 0] = rec[..., 1] + prep['bias'][:, None, None]
        out[..., 1] = rec[..., 3]
        out[..., 2] = rec[..., 0] - rec[..., 1]
        out[..., 3] = rec[..., 2] - rec[..., 3]
        return (out[:, :, self.eval_steps], out) if trajectory else out

    def residuals(self, terms_list, windows=None):
        """measured - predicted, (P, S, E, 4)."""
        sel = np.arange(len(self)) if windows is None else np.arange(len(self))[windows]
        return self.measured[sel][None] - self.predict(terms_list, sel)

    # ------------------------------------------------------------------ scales and gaps
    def set_scales(self, residual0, windows=None):
        """Whitening scales (E, 4) from the nominal residuals on the active windows off the caster
        (all active ones if none is): a robust RMS, sqrt(median(r^2) / 0.455) (= the standard
        deviation for Gaussian residuals), so that a few outlying windows do not set the
        yardstick. The caster holds the body still, so sitting windows would shrink the scales
        to the sensor noise there and make every moving window count as an outlier."""
        if windows is None:
            moving = self.active & (self.win_phase != 'sitting')
            windows = moving if np.any(moving) else self.active
        w = windows
        r = residual0[w] if residual0.ndim == 3 else residual0[0][w]
        self.scales = np.sqrt(np.median(r**2, axis=0) / 0.4549) + 1e-12
        return self.scales

    def window_loss(self, residuals):
        """Robust loss per window, (P, S): mean over points and channels of the soft-L1 function
        2 (sqrt(1 + z^2) - 1) of the whitened residual z (quadratic for |z| < 1, linear beyond)."""
        z2 = residuals / self.scales  # one temporary, worked in place (scans: 200 MB each)
        z2 *= z2
        z2 += 1.0
        np.sqrt(z2, out=z2)
        z2 -= 1.0
        z2 *= 2.0
        return np.mean(z2, axis=(-2, -1))


_POOLS = {}
#: parameter sets, batched predictions and element sub-steps (sets x windows x sub-steps) of all
#: replays of the process: what a benchmark counts, whatever the machine's load
PREDICTED = {'sets': 0, 'calls': 0, 'element_steps': 0}
#: a batch is split over the workers when it has at least this many elements (parameter sets x
#: windows) per worker: below it, the threads' hand-over costs more than the arithmetic
MIN_CHUNK_ELEMENTS = 2000
#: bytes of arrays each of the body and torque caches keeps: per variant an array of every
#: window's sub-steps (18k windows x 153 sub-steps: 22 MB a body field or a delay)
CACHE_BYTES = 300e6


def unique_terms(terms_list):
    """(the distinct parameter sets of `terms_list`, the index of each set among them): a set's
    prediction does not depend on the others predicted with it, so equal sets need one."""
    keys = [_terms_key(tm) for tm in terms_list]
    first = {}
    for i, k in enumerate(keys):
        first.setdefault(i if k is None else k, i)
    uniq = list(first.values())
    where = {i: n for n, i in enumerate(uniq)}
    back = np.array([where[i if k is None else first[k]] for i, k in enumerate(keys)], int)
    return [terms_list[i] for i in uniq], back


def _terms_key(terms: ModelTerms):
    """What a prediction depends on, hashable (None for a set with extra forces, callables that
    cannot be compared): equal keys, equal predictions bit for bit."""
    if terms.extra_forces:
        return None
    key = (
        terms.drive,
        terms.actuation_delay,
        terms.imu_pitch_bias,
        terms.inertia_add,
        terms.com_shift,
        terms.body_key(),
    )
    try:
        hash(key)
    except TypeError:
        return None
    return key


def _pool(workers: int) -> ThreadPoolExecutor:
    """One thread pool per size, shared by every replay of the process."""
    if workers not in _POOLS:
        _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix='replay')
    return _POOLS[workers]


def _lru_get(cache: dict, key):
    hit = cache.pop(key, None)
    if hit is not None:
        cache[key] = hit  # most recent last
    return hit


def _lru_put(cache: dict, key, value, size: int, max_bytes: float = math.inf):
    """Insert, then drop the least recently used entries beyond `size` entries or `max_bytes`
    of arrays (the newest always stays)."""
    cache[key] = value
    while len(cache) > size or (len(cache) > 1 and _nbytes(cache) > max_bytes):
        cache.pop(next(iter(cache)))


def _nbytes(cache: dict) -> int:
    return sum(
        x.nbytes
        for v in cache.values()
        for x in (v if isinstance(v, tuple) else (v,))
        if isinstance(x, np.ndarray)
    )


@dataclass
class _State:
    phi: np.ndarray
    q_base: np.ndarray
    dphi: np.ndarray
    dq_base: np.ndarray
    theta: np.ndarray
    tau: np.ndarray
    t: np.ndarray


def gap_metrics(replay: Replay, residuals, windows=None) -> dict:
    """Gap figures of one residual set (S, E, 4) on the given windows (default: the active ones):

    gap          RMS whitened prediction error over all windows, horizon points and the four
                 signals, each signal divided by its scale (``Replay.scales``: the nominal model's
                 robust RMS error for that signal and horizon point). Unitless: about 1 for the
                 nominal model (more with outlying windows), the share left for an extended model.
    rms_<signal> RMS error at the horizon, physical units (q_base rad, pitch_rate rad/s, wheel rad,
                 wheel_rate rad/s)
    mad_q_base   median absolute pitch error at the horizon (rad), insensitive to outlying windows
    """
    w = replay.active if windows is None else windows
    r = residuals[w]
    out = {'gap': math.nan}
    if replay.scales is not None and r.size:
        out['gap'] = float(np.sqrt(np.mean((r / replay.scales) ** 2)))
    for c, name in enumerate(CHANNELS):
        out[f'rms_{name}'] = float(np.sqrt(np.mean(r[:, -1, c] ** 2))) if r.size else math.nan
    out['mad_q_base'] = float(np.median(np.abs(r[:, -1, 0]))) if r.size else math.nan
    out['windows'] = int(r.shape[0])
    return out
