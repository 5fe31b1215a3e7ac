"""Records from files: the kit's hardware CSV logs and our MCAP bags (and a record back to a bag).

``load_csv_record`` (the kit's hardware logs, ~30 Hz, currents are COMMANDED), ``load_bag_record``
(our MCAP bags: /joint_states, /imu/data, /wheel_effort_cmd), ``load_measured`` (files or folders),
``save_bag`` (the inverse of ``load_bag_record``). Commands become wheel torques with the drive
train of krang_model.drivetrain.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from krang_adrc_controller.metrics import read_log_columns
from krang_bag.reader import iter_messages, read_float_arrays, read_joint_states
from krang_bag.writer import BagWriter, OfferedQos
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_core.names import IMU, JOINT_STATES, WHEEL_EFFORT_CMD, WHEEL_JOINTS
from krang_core.pitch import pitch_from_quaternion, pitch_quaternion

from .record import Record, resample, uniform_clock

#: pose-order joint columns of the kit's balancing CSVs
CSV_JOINT_COLUMNS = (
    ('q_waist_rad', 'q_torso_rad')
    + tuple(f'q_left_{i}_rad' for i in range(1, 8))
    + tuple(f'q_right_{i}_rad' for i in range(1, 8))
)


def _drive_constants():
    """(Kt, gear, current limit) of the drive train."""
    d = drivetrain(load_krang())
    return float(d.torque_constant), float(d.gear_ratio), float(d.current_limit)


def load_csv_record(path, rate_hz=None) -> Record:
    """A kit hardware log (krang_data/balancing_runs/*/*.csv).

    Columns used: dt_s (time = cumsum), i_cmd_left_A / i_cmd_right_A (COMMANDED motor currents,
    converted to wheel torque with the nominal Kt x gear of config/robot.yaml, clamp at the current
    limit), q_base_rad (IMU pitch), dtheta_com_rad_s (the Kalman-filtered IMU pitch rate),
    x_wheel_rad / dx_wheel_rad_s (encoders + IMU pitch, so wheel = x - q_base), and the 16 joints.
    The command logged in row k was sent in loop k, so it is held from t_k to t_k+1. The clock is
    resampled to uniform (the logs jitter between 1 and 42 ms)."""
    path = Path(path)
    need = (
        'dt_s',
        'i_cmd_left_A',
        'i_cmd_right_A',
        'dtheta_com_rad_s',
        'x_wheel_rad',
        'dx_wheel_rad_s',
        'q_base_rad',
    ) + CSV_JOINT_COLUMNS
    col = read_log_columns(path, need, min_rows=3)
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
    return Record(
        t=grid - grid[0],
        q_base=resample(t, qb, grid),
        pitch_rate=resample(t, rate, grid),
        wheel=resample(t, wheel, grid),
        wheel_rate=resample(t, wheel_rate, grid),
        joints=resample(t, joints, grid),
        cmd_t=t - grid[0],
        cmd_torque=cmd,
        torque_limit=ilim * kt * gear,
        name=path.stem,
        source=str(path),
        kind='hardware_csv',
        meta={
            'raw_samples': int(t.size),
            'raw_period_s': float(np.median(np.diff(t))),
            'command': 'commanded motor current x nominal Kt x gear',
        },
    )


def load_bag_record(
    path,
    rate_hz=None,
    *,
    joint_topic=JOINT_STATES,
    imu_topic=IMU,
    effort_topic=WHEEL_EFFORT_CMD,
) -> Record:
    """One of our MCAP bags (from `krang demo` / `mcap_recorder`).

    /joint_states: body joints (URDF names) + JLWheel/JRWheel (encoder angle relative to the body,
    positive rolls forward) with velocities; /imu/data: orientation = q_base about +y,
    angular_velocity.y = pitch rate; /wheel_effort_cmd: [left, right] N m at the wheels. Times are
    the bag's log times. Measurements go onto one uniform clock over the span every topic covers
    (default rate: the IMU's, at most 250 Hz); commands keep their own times."""
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
    if not np.all(np.isfinite(wvel)):  # no velocities published: differentiate the encoders
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
    return Record(
        t=grid - base,
        q_base=np.interp(grid, imu_t, imu_q),
        pitch_rate=np.interp(grid, imu_t, imu_r),
        wheel=np.interp(grid, jt, wpos),
        wheel_rate=np.interp(grid, jt, wvel),
        joints=resample(jt, jpos, grid),
        cmd_t=eff.t - origin - base,
        cmd_torque=cmd,
        torque_limit=ilim * kt * gear,
        name=Path(path).stem,
        source=str(path),
        kind='mcap',
        meta={'rate_hz': rate_hz, 'command': f'{effort_topic} (N m at the wheels)'},
    )


def save_bag(rec: Record, path, rate_hz: float | None = None) -> Path:
    """Write a record as an MCAP bag in our topic layout (the inverse of ``load_bag_record``):
    /joint_states (body joints + JLWheel/JRWheel, both wheels at the record's mean angle and rate),
    /imu/data (pitch quaternion about +y, pitch rate in angular_velocity.y) on the measurement
    clock (or resampled to `rate_hz`), /wheel_effort_cmd ([left, right] N m) at the command times.
    Times start at 1.7e9 s (an arbitrary wall-clock epoch)."""
    robot = load_krang()
    t0_ns = 1_700_000_000 * 10**9
    grid = rec.t if not rate_hz else np.arange(rec.t[0], rec.t[-1] + 1e-12, 1.0 / rate_hz)
    q = np.interp(grid, rec.t, rec.q_base)
    rate = np.interp(grid, rec.t, rec.pitch_rate)
    wheel = np.interp(grid, rec.t, rec.wheel)
    wrate = np.interp(grid, rec.t, rec.wheel_rate)
    joints = resample(rec.t, rec.joints, grid)
    names = list(robot.pose_joints) + list(WHEEL_JOINTS)
    events = [(tt, 0, k) for k, tt in enumerate(grid)] + [
        (tt, 1, k) for k, tt in enumerate(rec.cmd_t)
    ]
    events.sort()
    path = Path(path)
    with BagWriter(path) as bag:
        bag.add_topic(JOINT_STATES, 'sensor_msgs/msg/JointState')
        bag.add_topic(IMU, 'sensor_msgs/msg/Imu', offered_qos=[OfferedQos.sensor_data()])
        bag.add_topic(WHEEL_EFFORT_CMD, 'sensor_msgs/msg/JointState')
        for tt, kind, k in events:
            ns = t0_ns + int(round(tt * 1e9))
            if kind == 0:
                js = {
                    'name': names,
                    'position': [float(v) for v in joints[k]] + [float(wheel[k])] * 2,
                    'velocity': [0.0] * len(robot.pose_joints) + [float(wrate[k])] * 2,
                }
                bag.write_message(JOINT_STATES, js, ns)
                x, y, z, w = pitch_quaternion(float(q[k]))
                imu = {
                    'orientation': {'x': x, 'y': y, 'z': z, 'w': w},
                    'angular_velocity': {'y': float(rate[k])},
                }
                bag.write_message(IMU, imu, ns)
            else:
                cmd = {'name': list(WHEEL_JOINTS), 'effort': [float(v) for v in rec.cmd_torque[k]]}
                bag.write_message(WHEEL_EFFORT_CMD, cmd, ns)
    return path


def load_measured(paths, rate_hz=None) -> list[Record]:
    """Records from files (.csv kit logs, .mcap bags) and folders (each .csv/.mcap in them)."""
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
        first = [
            load_csv_record(f) if f.suffix.lower() == '.csv' else load_bag_record(f) for f in files
        ]
        rate_hz = 1.0 / float(np.median([r.period for r in first]))
    out = []
    for f in files:
        if f.suffix.lower() == '.mcap':
            out.append(load_bag_record(f, rate_hz))
        else:
            out.append(load_csv_record(f, rate_hz))
    return out
