"""Replay and align: measured data in one record type, and the nominal (or extended) model driven by
the same initial states, commands and poses.

Record
    ``Record``: one run on a uniform measurement clock (base pitch, pitch rate, wheel encoder angle
    and rate relative to the body, body joints) plus the commanded wheel torques at their own
    times (a zero-order hold: what the drives were asked for, in N m at the wheels).
    Loaders: ``load_csv_record`` (the kit's hardware logs, ~30 Hz, currents are COMMANDED),
    ``load_bag_record`` (our MCAP bags: /joint_states, /imu/data, /wheel_effort_cmd),
    ``load_measured`` (files or folders). ``simulate_record`` makes a record with ``KrangSim`` and the
    ADRC ``BalanceController`` (sit -> stand up -> balance, pose changes, a current excitation),
    with any hidden ``SimEffects``; the record it returns carries no trace of those effects.

Alignment
    Measured channels are linearly resampled to one uniform clock (the median sample period of the
    source, or ``rate_hz``). Commands stay a step function on their own clock: the replay integrates
    its exact average over each integration sub-step, so a 500 Hz command stream replayed on a
    200 Hz measurement grid loses nothing, and a fractional actuation delay is a smooth parameter.

Why short horizons (multiple shooting) and not one long rollout
    The balancing robot is an open-loop unstable pendulum (pole near +5 rad/s for the Table II
    pose). An open-loop rollout from the first sample with the measured commands diverges from any
    tiny error within a second or two, whatever the model, so its "gap" measures the instability and
    the initial condition, not the missing physics. A closed-loop re-simulation with our controller
    would not be the hardware's controller, and feedback hides the effects it compensates. So the
    replay starts a short prediction (default 0.3 s, about 1.5 time constants) at every measured
    state (every ``stride_s``), drives it with the measured commands and the measured pose, and
    compares the predicted signals with the measured ones along the horizon. Errors cannot compound
    across windows; a missing effect shows up as a systematic prediction error.

The model is ``krang_model.wip.WipDynamics`` (same equations, same semi-implicit Euler), evaluated
on numpy arrays: all windows and all parameter sets of a fit step at once.
"""
from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .effects import ModelTerms

#: pose-order joint columns of the kit's balancing CSVs
CSV_JOINT_COLUMNS = ('q_waist_rad', 'q_torso_rad') + tuple(f'q_left_{i}_rad' for i in range(1, 8)) + \
    tuple(f'q_right_{i}_rad' for i in range(1, 8))

PHASES = ('sitting', 'standing_up', 'balancing', 'moving_joints', 'sitting_down')
CHANNELS = ('q_base', 'pitch_rate', 'wheel', 'wheel_rate')
CHANNEL_UNITS = ('rad', 'rad/s', 'rad', 'rad/s')


# ----------------------------------------------------------------------------- record


@dataclass
class Record:
    """One measured run. Measurement arrays share the uniform clock ``t`` (s).

    q_base        IMU pitch (rad, hardware convention, FACTS §2)
    pitch_rate    IMU pitch rate (rad/s)
    wheel         mean wheel encoder angle RELATIVE TO THE BODY (rad); ground-referenced wheel angle
                  phi = wheel + q_base (the hardware's x_wheel_rad)
    wheel_rate    its rate (rad/s)
    joints        (N, 16) body joints in pose order (rad)
    cmd_t, cmd_torque   command times (s) and commanded wheel torques (M, 2) [left, right] in N m at
                  the wheels, each held until the next command (zero before the first)
    torque_limit  N m per wheel where the drives clamp (current limit x Kt x gear)
    """

    t: np.ndarray
    q_base: np.ndarray
    pitch_rate: np.ndarray
    wheel: np.ndarray
    wheel_rate: np.ndarray
    joints: np.ndarray
    cmd_t: np.ndarray
    cmd_torque: np.ndarray
    torque_limit: float = math.inf
    name: str = ''
    source: str = ''
    kind: str = ''
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.t = np.asarray(self.t, float)
        n = self.t.size
        for k in ('q_base', 'pitch_rate', 'wheel', 'wheel_rate'):
            v = np.asarray(getattr(self, k), float).ravel()
            if v.size != n:
                raise ValueError(f'{k}: {v.size} samples, t has {n}')
            setattr(self, k, v)
        self.joints = np.atleast_2d(np.asarray(self.joints, float))
        if self.joints.shape[0] != n:
            raise ValueError(f'joints: {self.joints.shape[0]} rows, t has {n}')
        self.cmd_t = np.asarray(self.cmd_t, float).ravel()
        self.cmd_torque = np.asarray(self.cmd_torque, float).reshape(-1, 2)
        if self.cmd_torque.shape[0] != self.cmd_t.size:
            raise ValueError('cmd_t and cmd_torque differ in length')
        if n < 3:
            raise ValueError('a record needs at least three samples')

    def __len__(self):
        return self.t.size

    @property
    def period(self) -> float:
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def phi(self):
        return self.wheel + self.q_base

    def command_at(self, t):
        """Commanded wheel torques (len(t), 2) at times t (zero-order hold)."""
        i = np.searchsorted(self.cmd_t, np.asarray(t, float), side='right') - 1
        out = np.where(i[:, None] >= 0, self.cmd_torque[np.clip(i, 0, None)], 0.0)
        return out

    def total_torque_at(self, t):
        lim = self.torque_limit
        c = np.clip(self.command_at(t), -lim, lim)
        return c.sum(axis=1)

    def slice(self, t0: float, t1: float) -> 'Record':
        """The part of the record between t0 and t1 (s, on its own clock)."""
        m = (self.t >= t0) & (self.t <= t1)
        mc = (self.cmd_t >= t0 - 1.0) & (self.cmd_t <= t1)
        return replace(self, t=self.t[m], q_base=self.q_base[m], pitch_rate=self.pitch_rate[m],
                       wheel=self.wheel[m], wheel_rate=self.wheel_rate[m], joints=self.joints[m],
                       cmd_t=self.cmd_t[mc], cmd_torque=self.cmd_torque[mc], meta=dict(self.meta))


def uniform_clock(t, rate_hz=None):
    """A uniform grid over [t0, t1] at rate_hz (default: the median sample rate of t)."""
    t = np.asarray(t, float)
    period = 1.0 / rate_hz if rate_hz else float(np.median(np.diff(t)))
    if not period > 0:
        raise ValueError('cannot build a clock: non-increasing times')
    n = int(math.floor((t[-1] - t[0]) / period + 1e-9)) + 1
    return t[0] + period * np.arange(n)


def resample(t_src, y_src, t_new):
    """Linear interpolation of y_src (N,) or (N, K) at t_new."""
    y = np.asarray(y_src, float)
    if y.ndim == 1:
        return np.interp(t_new, t_src, y)
    return np.column_stack([np.interp(t_new, t_src, y[:, k]) for k in range(y.shape[1])])


# ----------------------------------------------------------------------------- loaders


def _drive_constants():
    from krang_model.config import robot_config
    d = robot_config()['drivetrain']
    return float(d['torque_constant_Nm_per_A']), float(d['gear_ratio']), float(d['current_limit_A'])


def load_csv_record(path, rate_hz=None) -> Record:
    """A kit hardware log (krang_data/balancing_runs/*/*.csv).

    Columns used: dt_s (time = cumsum), i_cmd_left_A / i_cmd_right_A (COMMANDED motor currents,
    converted to wheel torque with the nominal Kt x gear of config/robot.yaml, clamp at the current
    limit), q_base_rad (IMU pitch), dtheta_com_rad_s (the Kalman-filtered IMU pitch rate),
    x_wheel_rad / dx_wheel_rad_s (encoders + IMU pitch, so wheel = x - q_base), and the 16 joints.
    The command logged in row k was sent in loop k, so it is held from t_k to t_k+1. The clock is
    resampled to uniform (the logs jitter between 1 and 42 ms)."""
    path = Path(path)
    with open(path, newline='') as f:
        header = next(csv.reader(f))
    need = ('dt_s', 'i_cmd_left_A', 'i_cmd_right_A', 'dtheta_com_rad_s', 'x_wheel_rad', 'dx_wheel_rad_s',
            'q_base_rad') + CSV_JOINT_COLUMNS
    missing = [c for c in need if c not in header]
    if missing:
        raise ValueError(f'{path}: not a balancing log, missing columns {missing}')
    data = np.loadtxt(path, delimiter=',', skiprows=1, ndmin=2)
    col = {c: data[:, header.index(c)] for c in need}
    t = np.cumsum(col['dt_s'])
    keep = np.concatenate([[True], np.diff(t) > 0])
    t = t[keep]
    kt, gear, ilim = _drive_constants()
    qb = col['q_base_rad'][keep]
    rate = col['dtheta_com_rad_s'][keep]
    wheel = col['x_wheel_rad'][keep] - qb
    wheel_rate = col['dx_wheel_rad_s'][keep] - rate
    joints = np.column_stack([col[c][keep] for c in CSV_JOINT_COLUMNS])
    cmd = np.column_stack([col['i_cmd_left_A'][keep], col['i_cmd_right_A'][keep]]) * kt * gear
    grid = uniform_clock(t, rate_hz)
    return Record(t=grid - grid[0], q_base=resample(t, qb, grid), pitch_rate=resample(t, rate, grid),
                  wheel=resample(t, wheel, grid), wheel_rate=resample(t, wheel_rate, grid),
                  joints=resample(t, joints, grid), cmd_t=t - grid[0], cmd_torque=cmd,
                  torque_limit=ilim * kt * gear, name=path.stem, source=str(path), kind='hardware_csv',
                  meta={'raw_samples': int(t.size), 'raw_period_s': float(np.median(np.diff(t))),
                        'command': 'commanded motor current x nominal Kt x gear'})


def load_bag_record(path, rate_hz=None, *, joint_topic='/joint_states', imu_topic='/imu/data',
                    effort_topic='/wheel_effort_cmd') -> Record:
    """One of our MCAP bags (from `krang demo` / `mcap_recorder`).

    /joint_states: body joints (URDF names) + JLWheel/JRWheel (encoder angle relative to the body,
    positive rolls forward) with velocities; /imu/data: orientation = q_base about +y,
    angular_velocity.y = pitch rate; /wheel_effort_cmd: [left, right] N m at the wheels. Times are
    the bag's log times. Measurements go onto one uniform clock over the span every topic covers
    (default rate: the IMU's, at most 250 Hz); commands keep their own times."""
    from krang_bag.reader import iter_messages, read_float_arrays, read_joint_states
    from krang_model.robot import load_krang
    from krang_ros.messages import pitch_from_quaternion
    from krang_ros.names import WHEEL_JOINTS
    robot = load_krang()
    js = read_joint_states(path, joint_topic)
    missing = [j for j in robot.pose_joints + WHEEL_JOINTS if j not in js.names]
    if missing:
        raise ValueError(f'{path}: {joint_topic} lacks joints {missing}')
    imu_ns, imu_q, imu_r = [], [], []
    for _, log_time, msg in iter_messages(path, [imu_topic]):
        o = msg.orientation
        imu_ns.append(int(log_time))
        imu_q.append(pitch_from_quaternion(o.x, o.y, o.z, o.w))
        imu_r.append(msg.angular_velocity.y)
    if len(imu_ns) < 3:
        raise ValueError(f'{path}: too few {imu_topic} messages')
    eff = read_float_arrays(path, effort_topic)
    # times relative to the first IMU message, from integer nanoseconds (float seconds since 1970
    # resolve only ~0.2 us and would make the median period, hence the clock, drift)
    order = np.argsort(imu_ns, kind='stable')
    ns = np.asarray(imu_ns, dtype=np.int64)[order]
    origin_ns = int(ns[0])
    origin = origin_ns / 1e9
    imu_t = (ns - origin_ns) / 1e9
    imu_q, imu_r = np.asarray(imu_q, float)[order], np.asarray(imu_r, float)[order]
    col = {n: i for i, n in enumerate(js.names)}
    jt = js.t - origin
    jpos = js.positions[:, [col[j] for j in robot.pose_joints]]
    wpos = js.positions[:, [col[w] for w in WHEEL_JOINTS]].mean(axis=1)
    wvel = js.velocities[:, [col[w] for w in WHEEL_JOINTS]].mean(axis=1)
    ok = np.all(np.isfinite(jpos), axis=1) & np.isfinite(wpos)
    jt, jpos, wpos, wvel = jt[ok], jpos[ok], wpos[ok], wvel[ok]
    if not np.all(np.isfinite(wvel)):      # no velocities published: differentiate the encoders
        wvel = np.gradient(wpos, jt)
    t0, t1 = max(imu_t[0], jt[0]), min(imu_t[-1], jt[-1])
    if not t1 > t0:
        raise ValueError(f'{path}: {imu_topic} and {joint_topic} do not overlap in time')
    if rate_hz is None:
        rate_hz = min(250.0, 1e9 / float(np.median(np.diff(ns))))
    grid = np.arange(t0, t1 + 1e-12, 1.0 / rate_hz)
    kt, gear, ilim = _drive_constants()
    cmd = eff.rows[:, :2] if eff.rows.size else np.zeros((0, 2))
    base = grid[0]
    return Record(t=grid - base, q_base=np.interp(grid, imu_t, imu_q), pitch_rate=np.interp(grid, imu_t, imu_r),
                  wheel=np.interp(grid, jt, wpos), wheel_rate=np.interp(grid, jt, wvel),
                  joints=resample(jt, jpos, grid), cmd_t=eff.t - origin - base, cmd_torque=cmd,
                  torque_limit=ilim * kt * gear, name=Path(path).stem, source=str(path), kind='mcap',
                  meta={'rate_hz': rate_hz, 'command': f'{effort_topic} (N m at the wheels)'})


def save_bag(rec: Record, path, rate_hz: float | None = None) -> Path:
    """Write a record as an MCAP bag in our topic layout (the inverse of ``load_bag_record``):
    /joint_states (body joints + JLWheel/JRWheel, both wheels at the record's mean angle and rate),
    /imu/data (pitch quaternion about +y, pitch rate in angular_velocity.y) on the measurement
    clock (or resampled to `rate_hz`), /wheel_effort_cmd ([left, right] N m) at the command times.
    Times start at 1.7e9 s (an arbitrary wall-clock epoch)."""
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64MultiArray
    from krang_bag.writer import BagWriter, OfferedQos
    from krang_model.robot import load_krang
    from krang_ros.messages import pitch_quaternion
    from krang_ros.names import WHEEL_JOINTS
    robot = load_krang()
    t0_ns = 1_700_000_000 * 10 ** 9
    grid = rec.t if not rate_hz else np.arange(rec.t[0], rec.t[-1] + 1e-12, 1.0 / rate_hz)
    q = np.interp(grid, rec.t, rec.q_base)
    rate = np.interp(grid, rec.t, rec.pitch_rate)
    wheel = np.interp(grid, rec.t, rec.wheel)
    wrate = np.interp(grid, rec.t, rec.wheel_rate)
    joints = resample(rec.t, rec.joints, grid)
    names = list(robot.pose_joints) + list(WHEEL_JOINTS)
    events = [(tt, 0, k) for k, tt in enumerate(grid)] + [(tt, 1, k) for k, tt in enumerate(rec.cmd_t)]
    events.sort()
    path = Path(path)
    with BagWriter(path) as bag:
        bag.add_topic('/joint_states', 'sensor_msgs/msg/JointState')
        bag.add_topic('/imu/data', 'sensor_msgs/msg/Imu', offered_qos=[OfferedQos.sensor_data()])
        bag.add_topic('/wheel_effort_cmd', 'std_msgs/msg/Float64MultiArray')
        for tt, kind, k in events:
            ns = t0_ns + int(round(tt * 1e9))
            if kind == 0:
                js = JointState()
                js.name = names
                js.position = [float(v) for v in joints[k]] + [float(wheel[k])] * 2
                js.velocity = [0.0] * len(robot.pose_joints) + [float(wrate[k])] * 2
                bag.write_message('/joint_states', js, ns)
                imu = Imu()
                x, y, z, w = pitch_quaternion(float(q[k]))
                imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = x, y, z, w
                imu.angular_velocity.y = float(rate[k])
                bag.write_message('/imu/data', imu, ns)
            else:
                bag.write_message('/wheel_effort_cmd', Float64MultiArray(data=[float(v) for v in rec.cmd_torque[k]]), ns)
    return path


def load_measured(paths, rate_hz=None) -> list[Record]:
    """Records from files (.csv kit logs, .mcap bags) and folders (every .csv/.mcap inside, sorted)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    files = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(q for q in p.rglob('*') if q.suffix.lower() in ('.csv', '.mcap'))
        elif p.exists():
            files.append(p)
        else:
            raise FileNotFoundError(f'no such file or folder: {p}')
    if not files:
        raise ValueError(f'no .csv or .mcap data in {", ".join(map(str, paths))}')
    if rate_hz is None and len(files) > 1:
        # one clock for all records (the replay integrates every window with the same sub-step):
        # the median native rate of the files
        first = [load_csv_record(f) if f.suffix.lower() == '.csv' else load_bag_record(f) for f in files]
        rate_hz = 1.0 / float(np.median([r.period for r in first]))
    out = []
    for f in files:
        if f.suffix.lower() == '.mcap':
            out.append(load_bag_record(f, rate_hz))
        else:
            out.append(load_csv_record(f, rate_hz))
    return out


# ----------------------------------------------------------------------------- phases


def label_phases(rec: Record, caster_pitch: float = -1.7628, *, sit_band=0.015, still_rate=0.1,
                 still_s=0.5, joint_rate=0.02) -> np.ndarray:
    """Phase of every sample (strings of PHASES), from the measurements alone (the hardware logs
    have no mode column):

    * sitting: q_base on the record's low plateau (within ``sit_band`` of its 1st percentile) when
      that plateau is near the caster pitch (within 0.08 rad; an IMU bias moves it);
    * standing_up: from leaving the plateau until |pitch rate| < ``still_rate`` for ``still_s``;
    * sitting_down: from the last such quiet spell to the plateau;
    * moving_joints: otherwise, while any body joint moves faster than ``joint_rate`` rad/s;
    * balancing: the rest.
    """
    n = len(rec)
    labels = np.full(n, 'balancing', dtype=object)
    q = rec.q_base
    low = float(np.percentile(q, 1))
    sitting = np.zeros(n, bool)
    if low < caster_pitch + 0.08:
        sitting = q < low + sit_band
    dt = rec.period
    w = max(1, int(round(still_s / dt)))
    calm = np.abs(rec.pitch_rate) < still_rate
    # calm_run[i]: samples i-w+1..i all calm
    cs = np.concatenate([[0], np.cumsum(calm)])
    calm_run = np.zeros(n, bool)
    calm_run[w - 1:] = (cs[w:] - cs[:-w]) == w
    # joint motion (smoothed over 0.1 s)
    k = max(1, int(round(0.1 / dt)))
    jd = np.abs(rec.joints[k:] - rec.joints[:-k]).max(axis=1) / (k * dt) if n > k else np.zeros(0)
    moving = np.zeros(n, bool)
    moving[k // 2:k // 2 + jd.size] = jd > joint_rate
    i = 0
    while i < n:
        if sitting[i]:
            labels[i] = 'sitting'
            i += 1
            continue
        j = i
        while j < n and not sitting[j]:
            j += 1
        # non-sitting stretch [i, j)
        stretch = np.arange(i, j)
        if i > 0:       # came from sitting: standing up until a calm spell completes
            quiet = np.flatnonzero(calm_run[i:j])
            end_up = i + (quiet[0] if quiet.size else j - i)
            labels[i:end_up] = 'standing_up'
        else:
            end_up = i
        if j < n:       # goes back to sitting: sitting down after the last calm spell
            quiet = np.flatnonzero(calm_run[end_up:j])
            start_down = end_up + quiet[-1] + 1 if quiet.size else end_up
            labels[start_down:j] = 'sitting_down'
        else:
            start_down = j
        mid = stretch[(stretch >= end_up) & (stretch < start_down)]
        labels[mid[moving[mid]]] = 'moving_joints'
        i = j
    return labels


# ----------------------------------------------------------------------------- nominal model


@dataclass
class NominalModel:
    """The model the data are compared with: robot (pinocchio), mass model beta, drive train."""

    robot: object
    beta: np.ndarray
    drive: object
    beta_source: str = ''

    @classmethod
    def default(cls, beta_path=None, **drive_overrides) -> 'NominalModel':
        """Krang with config/sim_true_beta.yaml (the physically consistent fit to the real
        balanced poses: the project's best mass model) and the drive train of config/robot.yaml."""
        from krang_model.beta import load_beta
        from krang_model.config import config_path
        from krang_model.robot import load_krang
        from krang_model.drivetrain import drivetrain
        robot = load_krang()
        path = Path(beta_path) if beta_path else Path(config_path('sim_true_beta.yaml'))
        return cls(robot, load_beta(path, robot), drivetrain(robot, **drive_overrides), str(path))

    def terms(self) -> ModelTerms:
        return ModelTerms.nominal(self.drive)


def reduce_poses(robot, joints, beta, links=()):
    """Vectorised ``krang_model.wip.reduce_pose`` for N poses (rows of joints, pose order).

    Returns dict: mass (scalar, wheels excluded), my, mz (N,) the mass moment in the base frame
    (y, z; kg m), inertia (N,) about the axle (kg m^2), and for each link in `links`:
    '<link>:R', '<link>:p' (its frame rotation (N,3,3) and origin (N,3)), '<link>:m' (its mass)."""
    from krang_model.kinematics import body_placements
    joints = np.atleast_2d(np.asarray(joints, float))
    rot, trans = body_placements(robot, joints)
    b4 = np.asarray(beta, float).reshape(-1, 4)
    ids = [i for i in range(robot.n_bodies) if i not in robot.wheel_body_ids]
    m = b4[ids, 0]
    local = np.divide(b4[ids, 1:], m[:, None], out=np.zeros((len(ids), 3)), where=m[:, None] != 0)
    com = trans[:, ids] + np.einsum('nbij,bj->nbi', rot[:, ids], local)          # (N, B, 3)
    moment = np.einsum('b,nbi->ni', m, com)
    inert = np.stack([robot.body_inertias[i] for i in ids])                     # (B, 3, 3)
    r0 = rot[:, ids, 0, :]                                                       # (N, B, 3)
    rot_term = np.einsum('nbi,bij,nbj->nb', r0, inert, r0)
    inertia = (rot_term + m[None] * (com[..., 1] ** 2 + com[..., 2] ** 2)).sum(axis=1)
    out = {'mass': float(m.sum()), 'my': moment[:, 1], 'mz': moment[:, 2], 'inertia': inertia}
    for link in links:
        i = robot.body_names.index(link)
        out[f'{link}:R'] = rot[:, i]
        out[f'{link}:p'] = trans[:, i]
        mi = b4[i, 0]
        out[f'{link}:m'] = float(mi)
        out[f'{link}:com'] = trans[:, i] + (rot[:, i] @ (b4[i, 1:] / mi) if mi else 0.0)
    return out


# ----------------------------------------------------------------------------- replay


@dataclass
class ReplayConfig:
    horizon_s: float = 0.3          # prediction horizon of each window
    stride_s: float = 0.05          # a window starts every stride
    n_eval: int = 3                 # comparison points along the horizon (equally spaced, last = H)
    substep_s: float = 0.002        # largest integration step
    smooth_s: float = 0.02          # half-width of the gyro-aided smoothing of the measured pitch
    body_period_s: float = 0.02     # pose reduction period while joints move
    pose_delay_s: float = 0.0       # the body follows the measured joints this much later
    caster_margin: float = 0.02     # windows that come this close to the caster pitch are 'sitting'
    max_windows: int = 4000         # per record (stride is widened beyond)


@dataclass
class _Rec:
    """Per-record precomputations."""
    record: Record
    labels: np.ndarray
    tb: np.ndarray          # body-table times
    jb: np.ndarray          # body-table joints (K, 16)
    ct: np.ndarray          # command breakpoints
    cu: np.ndarray          # total clamped torque after each breakpoint
    cc: np.ndarray          # cumulative integral at breakpoints
    lr: np.ndarray          # (M, 2) per-wheel commands at the breakpoints (for other clamps)


class Replay:
    """Multiple-shooting replay of records under the nominal model or any extension of it.

    ``predict(terms_list)`` -> predicted measurements (P, S, E, 4) for P parameter sets, S windows,
    E points along the horizon, channels CHANNELS; ``measured`` is (S, E, 4); ``residuals`` the
    difference. Window metadata: ``win_record``, ``win_t`` (start time), ``win_phase``.
    """

    def __init__(self, records, model: NominalModel, config: ReplayConfig | None = None, phases=None):
        self.model = model
        self.cfg = cfg = config or ReplayConfig()
        self.records = list(records) if isinstance(records, (list, tuple)) else [records]
        d = model.drive
        self.g = d.gravity
        self.mw, self.iw, self.jr = d.wheel_mass, d.wheel_inertia, d.reflected_rotor_inertia
        self.caster = (d.caster_pitch, d.caster_stiffness, d.caster_damping)
        self._recs = []
        starts, t_start, rec_id, phase, inits, meas = [], [], [], [], [], []
        self._h = None
        for ri, rec in enumerate(self.records):
            h, n_steps, step_samples, eval_samples = self._grid(rec.period)
            if self._h is None:
                self._h, self._n_steps = h, n_steps
                self._horizon = n_steps * h
                self.eval_steps = np.round(eval_samples / step_samples).astype(int)
            elif abs(h - self._h) > 1e-6 * self._h or n_steps != self._n_steps:
                raise ValueError('records with different sample periods: resample them to one rate '
                                 f'({rec.name}: {rec.period:.4g} s vs {self.records[0].period:.4g} s)')
            n_h = int(eval_samples[-1])
            eval_off = eval_samples
            labels = label_phases(rec, d.caster_pitch)
            stride = max(1, int(round(cfg.stride_s / rec.period)))
            ks = np.arange(0, len(rec) - n_h, stride)
            if ks.size > cfg.max_windows:
                ks = ks[np.linspace(0, ks.size - 1, cfg.max_windows).astype(int)]
            eval_off = np.round(np.linspace(n_h / cfg.n_eval, n_h, cfg.n_eval)).astype(int)
            qs = self._smooth_pitch(rec)
            sig = np.column_stack([qs, rec.pitch_rate, rec.wheel, rec.wheel_rate])
            # windows touching the caster are 'sitting' whatever the label at their start
            win_min = np.array([rec.q_base[k:k + n_h + 1].min() for k in ks]) if ks.size else np.zeros(0)
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
            # commands: total clamped torque as a step function and its running integral
            lim = rec.torque_limit
            ct = rec.cmd_t
            lr = rec.cmd_torque if ct.size else np.zeros((0, 2))
            ct = np.concatenate([[ct[0] - 1e6 if ct.size else rec.t[0] - 1e6], ct, [rec.t[-1] + 1e6]])
            lr = np.concatenate([np.zeros((1, 2)), lr, lr[-1:] if lr.size else np.zeros((1, 2))])
            cu = np.clip(lr, -lim, lim).sum(axis=1)
            cc = np.concatenate([[0.0], np.cumsum(cu[:-1] * np.diff(ct))])
            tb, jb = self._body_samples(rec)
            self._recs.append(_Rec(rec, labels, tb, jb, ct, cu, cc, lr))
        self.win_k = np.concatenate(starts)
        self.win_t = np.concatenate(t_start)
        self.win_record = np.concatenate(rec_id)
        self.win_phase = np.concatenate(phase)
        self.init = np.concatenate(inits)                  # (S, 4) measured state at the start
        self.measured = np.concatenate(meas)               # (S, E, 4)
        self.eval_tau = self.eval_steps * self._h
        # sub-step times (S, J+1) and body-table interpolation
        self.sub_t = self.win_t[:, None] + self._h * np.arange(self._n_steps + 1)[None]
        self._body_cache = {}
        self._reduce_cache = {}
        self._torque_cache = {}
        self.payload_links = ('lGripper', 'rGripper')
        self.select(phases)
        self.scales = None
        self.timing = {}

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
        """Restrict ``active`` (the windows fits use) to these phases (None: all but sitting)."""
        if phases is None:
            phases = tuple(p for p in PHASES if p != 'sitting')
        self.phases = tuple(phases)
        self.active = np.isin(self.win_phase, self.phases)
        return self.active

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
        a = np.concatenate([[0.0], np.cumsum(0.5 * (rec.pitch_rate[1:] + rec.pitch_rate[:-1]) * np.diff(rec.t))])
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
        jb = rec.joints[:n * per].reshape(n, per, -1).mean(axis=1)
        tb = rec.t[:n * per].reshape(n, per).mean(axis=1) + delay
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

    def _reduction(self, offsets_key):
        """Per record: the pose reduction (reduce_poses with every link placement a payload may
        need) at the body-table joints shifted by the encoder offsets (cached by offsets)."""
        hit = _lru_get(self._reduce_cache, offsets_key)
        if hit is not None:
            return hit
        robot, beta = self.model.robot, self.model.beta
        out = []
        for r in self._recs:
            joints = r.jb.copy()
            for jname, off in offsets_key:
                joints[:, robot.pose_joints.index(jname)] -= off      # true = measured - offset
            out.append(reduce_poses(robot, joints, beta, self.payload_links))
        _lru_put(self._reduce_cache, offsets_key, out, 64)
        return out

    def _body_arrays(self, terms: ModelTerms):
        """(mass_total (S,J), M*l (S,J), offset (S,J), inertia (S,J)) for this body variant,
        at the mid-point of every sub-step (cached by terms.body_key())."""
        key = terms.body_key()
        hit = _lru_get(self._body_cache, key)
        if hit is not None:
            return hit
        missing = {p[0] for p in terms.payloads} - set(self.payload_links)
        if missing:
            self.payload_links = tuple(sorted(set(self.payload_links) | missing))
            self._reduce_cache.clear()
        reds = self._reduction(key[1])
        still = all(len(r.tb) == 1 for r in self._recs)
        # a record whose pose never moves needs one value per window, broadcast over sub-steps
        mid = self.sub_t[:, :1] if still else 0.5 * (self.sub_t[:, 1:] + self.sub_t[:, :-1])
        out = [np.empty(mid.shape) for _ in range(4)]
        for ri, r in enumerate(self._recs):
            sel = self.win_record == ri
            if not np.any(sel):
                continue
            red = reds[ri]
            mass = np.full(len(r.tb), red['mass'])
            my, mz, inertia = red['my'].copy(), red['mz'].copy(), red['inertia'].copy()
            for link, point, kg in terms.payloads:
                if not kg:
                    continue
                p = red[f'{link}:p'] + red[f'{link}:R'] @ np.asarray(point, float)
                ml, cl = red[f'{link}:m'], red[f'{link}:com']
                s0 = ml * cl
                s1 = s0 + kg * p
                # the simulator adds the payload to the link's beta (krang_sim.physics.payload_beta)
                # and reduces again: the link's parallel-axis term becomes |s1|^2 / (m + kg)
                inertia += (s1[:, 1] ** 2 + s1[:, 2] ** 2) / (ml + kg) - (s0[:, 1] ** 2 + s0[:, 2] ** 2) / ml
                mass += kg
                my += kg * p[:, 1]
                mz += kg * p[:, 2]
            ml_ = np.hypot(my, mz)                 # M * l
            off = np.arctan2(-mz, my)
            tq = mid[sel]
            for k, v in enumerate((mass, ml_, off, inertia)):
                out[k][sel] = v[0] if v.size == 1 else np.interp(tq, r.tb, v)
        _lru_put(self._body_cache, key, out, 24)
        return out

    def _torque_arrays(self, delay: float, current_limit=None):
        """Average commanded total torque over each sub-step, delayed by `delay` (S, J); with a
        `current_limit` (A) the per-wheel commands are clamped there instead of at the record's
        torque limit."""
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
            cu, cc = r.cu, r.cc
            if current_limit is not None:
                lim = min(r.record.torque_limit, current_limit * k_motor)
                cu = np.clip(r.lr, -lim, lim).sum(axis=1)
                cc = np.concatenate([[0.0], np.cumsum(cu[:-1] * np.diff(r.ct))])
            # exact integral of the step function: C(t) = cc[i] + cu[i] (t - ct[i])
            tt = self.sub_t[sel] - delay
            i = np.clip(np.searchsorted(r.ct, tt, side='right') - 1, 0, r.ct.size - 1)
            c = cc[i] + cu[i] * (tt - r.ct[i])
            tq[sel] = np.diff(c, axis=1) / self._h
        _lru_put(self._torque_cache, key, tq, 12)
        return tq

    # ------------------------------------------------------------------ prediction
    def predict(self, terms_list, windows=None, trajectory=False, max_elements: int = 300_000):
        """``_predict`` in chunks of windows so that (parameter sets x windows) stays below
        `max_elements` (memory)."""
        if isinstance(terms_list, ModelTerms):
            terms_list = [terms_list]
        sel = np.arange(len(self)) if windows is None else np.arange(len(self))[windows]
        chunk = max(1, max_elements // max(1, len(terms_list)))
        if sel.size <= chunk:
            return self._predict(terms_list, sel, trajectory)
        parts = [self._predict(terms_list, sel[i:i + chunk], trajectory) for i in range(0, sel.size, chunk)]
        if trajectory:
            return (np.concatenate([p[0] for p in parts], axis=1), np.concatenate([p[1] for p in parts], axis=1))
        return np.concatenate(parts, axis=1)

    def _predict(self, terms_list, windows=None, trajectory=False):
        """Predicted measurements (P, S, E, 4) for each ModelTerms in `terms_list` (windows: an
        index/mask into the windows, default all). With trajectory=True also returns the sub-step
        states (P, S, J+1, 4) as measured channels.

        All P parameter sets step together; body variants (payloads, encoder offsets) and delays
        are computed once per distinct value and gathered per step."""
        t_start = time.perf_counter()
        if isinstance(terms_list, ModelTerms):
            terms_list = [terms_list]
        sel = np.arange(len(self)) if windows is None else np.arange(len(self))[windows]
        P, S, J = len(terms_list), sel.size, self._n_steps
        h, g, mw, iw, jr = self._h, self.g, self.mw, self.iw, self.jr
        col = lambda name: np.array([getattr(tm, name) for tm in terms_list], float)[:, None]  # noqa: E731
        r, alpha, ts = col('wheel_radius'), col('floor_slope'), col('torque_scale')
        b, bg, tc, bias = col('viscous_friction'), col('ground_viscous'), col('coulomb_friction'), col('imu_pitch_bias')
        # distinct body variants: (J, n_u, S) arrays, gathered per step when n_u > 1
        bkeys = [tm.body_key() for tm in terms_list]
        ukeys = list(dict.fromkeys(bkeys))
        bidx = np.array([ukeys.index(k) for k in bkeys]) if len(ukeys) > 1 else None
        first = {k: terms_list[bkeys.index(k)] for k in ukeys}
        bodies = [self._body_arrays(first[k]) for k in ukeys]
        mass = np.array([bd[0][0, 0] if bd[0].size else 0.0 for bd in bodies])[bidx if bidx is not None else [0]][:, None]
        mlen = np.stack([bd[1][sel].T for bd in bodies], axis=1)              # (J or 1, n_u, S)
        off = np.stack([bd[2][sel].T for bd in bodies], axis=1)
        m22s = np.stack([bd[3][sel].T for bd in bodies], axis=1) + jr
        jb_last = mlen.shape[0] - 1
        delays = [(tm.actuation_delay, tm.current_limit) for tm in terms_list]
        udel = list(dict.fromkeys(delays))
        didx = np.array([udel.index(d) for d in delays]) if len(udel) > 1 else None
        tq_u = np.stack([self._torque_arrays(*d)[sel].T for d in udel], axis=1)  # (J, n_d, S)
        ia = col('inertia_add')
        any_ia = bool(np.any(ia))
        dl = col('com_shift')
        any_dl = bool(np.any(dl))
        m11 = (mass + mw) * r ** 2 + iw + jr                                   # (P, 1)
        slope = bool(np.any(alpha))
        grade = (mass + mw) * g * np.sin(alpha) * r if slope else None
        # initial state (true pitch = measured - bias)
        x0 = self.init[sel]
        qb = x0[:, 0][None] - bias + np.zeros((P, 1))
        dqb = x0[:, 1][None] + np.zeros((P, 1))
        phi = qb + x0[:, 2][None]
        dphi = dqb + x0[:, 3][None]
        c_pitch, c_k, c_d = self.caster
        extra = [tm.extra_forces for tm in terms_list]
        any_extra = any(extra)
        out = np.empty((P, S, len(self.eval_steps), 4))
        traj = np.empty((P, S, J + 1, 4)) if trajectory else None
        if trajectory:
            traj[:, :, 0] = np.stack([qb + bias, dqb, phi - qb, dphi - dqb], axis=-1)
        e_index = {int(s): i for i, s in enumerate(self.eval_steps)}
        coul = bool(np.any(tc))
        ground = bool(np.any(bg))
        g_over = r * (1.0 / g)
        for j in range(J):
            jb = j if j < jb_last else jb_last
            if bidx is None:
                off_j, mgl_j, m22_j = off[jb], mlen[jb] * g, m22s[jb]
            else:
                off_j, mgl_j, m22_j = off[jb][bidx], mlen[jb][bidx] * g, m22s[jb][bidx]
            if any_ia:
                m22_j = m22_j + ia
            if any_dl:      # CoM moved by dl along its direction: M l -> M (l + dl), I += M ((l+dl)^2 - l^2)
                l_j = mgl_j / (g * mass)
                mgl_j = mgl_j + (mass * g) * dl
                m22_j = m22_j + mass * dl * (2.0 * l_j + dl)
            tau = (tq_u[j] if didx is None else tq_u[j][didx]) * ts
            th = qb + off_j
            s_th = np.sin(th)
            if slope:
                ta = th + alpha
                s_ta, c_ta = np.sin(ta), np.cos(ta)
            else:
                s_ta, c_ta = s_th, np.cos(th)
            mrl = mgl_j * g_over
            rel = dphi - dqb
            brel = b * rel
            fr = brel
            if ground:
                fr = fr + bg * dphi
            if coul:
                fr = fr + 2.0 * tc * np.tanh(rel * 100.0)
            m12 = mrl * c_ta - jr
            f1 = mrl * s_ta * dqb * dqb + tau - fr
            if slope:
                f1 = f1 - grade
            f2 = mgl_j * s_th - tau + brel
            if qb.min() < c_pitch:
                pen = c_pitch - qb
                f2 = f2 + np.where(pen > 0, np.maximum(0.0, c_k * pen - c_d * dqb), 0.0)
            if any_extra:
                for p, fl in enumerate(extra):
                    if not fl:
                        continue
                    st = _State(phi[p], qb[p], dphi[p], dqb[p], th[p], tau[p], self.sub_t[sel, j])
                    for fn in fl:
                        a1, a2 = fn(st)
                        f1[p] = f1[p] + a1
                        f2[p] = f2[p] + a2
            inv = 1.0 / (m11 * m22_j - m12 * m12)
            dphi = dphi + (h * inv) * (m22_j * f1 - m12 * f2)
            dqb = dqb + (h * inv) * (m11 * f2 - m12 * f1)
            phi = phi + h * dphi
            qb = qb + h * dqb
            if trajectory:
                traj[:, :, j + 1] = np.stack([qb + bias, dqb, phi - qb, dphi - dqb], axis=-1)
            e = e_index.get(j + 1)
            if e is not None:
                out[:, :, e, 0] = qb + bias
                out[:, :, e, 1] = dqb
                out[:, :, e, 2] = phi - qb
                out[:, :, e, 3] = dphi - dqb
        self.timing['predict_s'] = self.timing.get('predict_s', 0.0) + time.perf_counter() - t_start
        self.timing['predict_calls'] = self.timing.get('predict_calls', 0) + 1
        self.timing['predict_sets'] = self.timing.get('predict_sets', 0) + P
        return (out, traj) if trajectory else out

    def residuals(self, terms_list, windows=None):
        """measured - predicted, (P, S, E, 4)."""
        sel = np.arange(len(self)) if windows is None else np.arange(len(self))[windows]
        return self.measured[sel][None] - self.predict(terms_list, sel)

    # ------------------------------------------------------------------ scales and gaps
    def set_scales(self, residual0, windows=None):
        """Whitening scales (E, 4) from the nominal residuals on the active windows: a robust RMS,
        sqrt(median(r^2) / 0.455) (= the standard deviation for Gaussian residuals), so that a few
        outlying windows do not set the yardstick."""
        w = self.active if windows is None else windows
        r = residual0[w] if residual0.ndim == 3 else residual0[0][w]
        self.scales = np.sqrt(np.median(r ** 2, axis=0) / 0.4549) + 1e-12
        return self.scales

    def window_loss(self, residuals):
        """Robust loss per window, (P, S): mean over points and channels of the soft-L1 function
        2 (sqrt(1 + z^2) - 1) of the whitened residual z (quadratic for |z| < 1, linear beyond)."""
        z2 = (residuals / self.scales) ** 2
        return np.mean(2.0 * (np.sqrt(1.0 + z2) - 1.0), axis=(-2, -1))


def _lru_get(cache: dict, key):
    hit = cache.pop(key, None)
    if hit is not None:
        cache[key] = hit         # most recent last
    return hit


def _lru_put(cache: dict, key, value, size: int):
    cache[key] = value
    while len(cache) > size:
        cache.pop(next(iter(cache)))


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
    rms_<signal> RMS error at the horizon in physical units (q_base rad, pitch_rate rad/s, wheel rad,
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


# ----------------------------------------------------------------------------- synthetic data


#: a default pose programme for simulate_record: joint deltas (rad) from the start pose, in
#: pose order (JWaist, JTorso, LJ1..LJFT, RJ1..RJFT); each held for a few seconds in turn
DEFAULT_POSE_PROGRAMME = (
    {'LJ1': 0.6, 'LJ2': 0.5, 'JWaist': -0.12},
    {'RJ1': -0.6, 'RJ2': -0.5, 'JTorso': 0.5, 'LJ4': 0.6},
    {'JWaist': -0.25, 'LJ2': -0.4, 'RJ4': -0.6},
    {},
)


def simulate_record(effects=None, *, seconds: float = 30.0, seed: int = 0, start_pose=None,
                    programme=DEFAULT_POSE_PROGRAMME, hold_s: float = 3.0, excitation_a: float = 3.0,
                    noise=None, log_rate_hz: float | None = None, sit_down: bool | None = None,
                    controller_config=None, true_beta=None, name: str = 'sim') -> Record:
    """A measured-looking record from the simulated Krang (krang_sim.physics) under the ADRC
    BalanceController with the NOMINAL model, with hidden ``effects`` (a SimEffects) in the plant.

    Sequence: sit on the caster for 1 s, enable (stand up, then balance), after 1.5 s of balance walk
    through ``programme`` (pose changes, each held ``hold_s``), with a random +-``excitation_a`` A
    telegraph added to both wheel currents while balancing; if ``sit_down`` (default: records of
    20 s or more) return to the start pose and sit down for the last part. The record logs what the
    controller and the hardware would: the noisy sensor samples at the controller rate (or
    ``log_rate_hz``) and the commanded currents (controller output + excitation) as wheel torques at
    every control step. Nothing in the record says which effect was hidden."""
    from krang_adrc_controller.controller import BalanceController, ControllerConfig
    from krang_model.beta import load_beta
    from krang_model.config import config_path
    from krang_model.robot import load_krang
    from krang_sim.closed_loop import TABLE2_POSE, FastKrangSim
    from krang_sim.physics import SensorNoise, SimConfig, SimEffects
    robot = load_krang()
    beta = load_beta(config_path('sim_true_beta.yaml'), robot)
    truth = beta if true_beta is None else np.asarray(true_beta, float)
    pose0 = np.array(TABLE2_POSE if start_pose is None else start_pose, float)
    sim = FastKrangSim(robot, truth, pose0, config=SimConfig(effects=effects or SimEffects(),
                                                              noise=noise or SensorNoise(), seed=seed))
    # the dataclass defaults, not config/controller.yaml: test data must not change when the
    # deployed controller is retuned. The paper's law, as on the hardware runs (no balance-point observer).
    ctl = BalanceController(robot, beta, controller_config or ControllerConfig(balance_point_observer=False))
    n_sub = int(round(ctl.h / sim.config.dt))
    rng = np.random.default_rng(seed + 7919)
    k_motor = ctl.k_motor
    sit_down = seconds >= 20.0 if sit_down is None else sit_down
    steps = int(round(seconds / ctl.h))
    log = {k: np.empty(steps) for k in ('t', 'q', 'r', 'w', 'wr', 'il', 'ir', 'mode')}
    joints = np.empty((steps, len(pose0)))
    exc, exc_until = 0.0, 0.0
    t_balance = None
    prog = [dict(p) for p in programme]
    next_pose_t = math.inf
    sat_down = False
    modes = {'safe_stop': -1, 'sit': 0, 'stand_up': 1, 'balance': 2, 'sit_down': 3}
    for k in range(steps):
        if k * ctl.h >= 1.0 and not ctl.enabled and not sat_down:
            ctl.set_enabled(True)
        s = sim.control_sample()
        out = ctl.step(s, now=sim.t)
        t = sim.t
        if out.mode == 'balance' and t_balance is None:
            t_balance = t
            next_pose_t = t + 1.5
        if t >= next_pose_t and not sat_down:
            if prog:
                delta = prog.pop(0)
                target = pose0.copy()
                for jn, v in delta.items():
                    target[robot.pose_joints.index(jn)] += v
                sim.command_joints(target)
                next_pose_t = t + hold_s + float(np.max(np.abs(target - sim.joints) / robot.velocity_limit))
            else:
                next_pose_t = math.inf
        if sit_down and not sat_down and t >= seconds - 6.0 and out.mode == 'balance':
            if not sim.joints_moving and np.allclose(sim.joint_targets, pose0):
                ctl.request_sit()
                sat_down = True
            elif not np.allclose(sim.joint_targets, pose0):
                sim.command_joints(pose0)
        il, ir = out.current_left, out.current_right
        if out.mode == 'balance' and excitation_a:
            if t >= exc_until:
                exc = excitation_a * rng.choice([-1.0, 1.0])
                exc_until = t + rng.uniform(0.1, 0.5)
            il, ir = il + exc, ir + exc
        sim.command_currents(il, ir)
        log['t'][k], log['q'][k], log['r'][k] = s.t, s.q_base, s.pitch_rate
        log['w'][k] = 0.5 * (s.wheel_left + s.wheel_right)
        log['wr'][k] = 0.5 * (s.wheel_left_rate + s.wheel_right_rate)
        log['il'][k], log['ir'][k] = il, ir
        log['mode'][k] = modes.get(out.mode, -2)
        joints[k] = s.joints
        sim.step(n_sub)
    t = log['t']
    cmd = np.column_stack([log['il'], log['ir']]) * k_motor
    if log_rate_hz:
        grid = np.arange(t[0], t[-1] + 1e-12, 1.0 / log_rate_hz)
        pick = lambda v: np.interp(grid, t, v)  # noqa: E731
        meas = dict(t=grid, q_base=pick(log['q']), pitch_rate=pick(log['r']), wheel=pick(log['w']),
                    wheel_rate=pick(log['wr']), joints=resample(t, joints, grid))
    else:
        meas = dict(t=t, q_base=log['q'], pitch_rate=log['r'], wheel=log['w'], wheel_rate=log['wr'],
                    joints=joints)
    return Record(**meas, cmd_t=t, cmd_torque=cmd, torque_limit=ctl.config.current_limit_a * k_motor,
                  name=name, source='krang_sim', kind='sim',
                  meta={'controller_rate_hz': 1.0 / ctl.h, 'mode': log['mode'], 'mode_t': t.copy(),
                        'seconds': seconds, 'seed': seed, 'stood_up_s': t_balance})
