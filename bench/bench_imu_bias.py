"""IMU pitch filter: gyro-bias tracking speed against acceleration-induced pitch error.

    .venv/bin/python bench/bench_imu_bias.py [--out docs/imu_bias_tradeoff.png]

For a sweep of the bias process noise (imu.kalman.bias_process_noise; the configured value is
marked), the configured filter (krang_can_bridge/imu_filter.py) is fed DMU samples at 200 Hz,
LSB-quantised, without noise (the noise is the tests' business; here it would only blur the
curves). It prints and plots:

* the tracking time constant: time for the bias estimate to reach 63 % of an unannounced
  0.01 rad/s step of the gyro bias, robot still on its caster;
* the pitch error left 90-120 s after that step (requirement: <= 2 mrad), and its peak;
* the peak pitch error while balancing: a closed-loop trajectory (krang_sim.closed_loop: true
  pitch, rate and axle acceleration; stand-up, then the position reference moving +-10 cm at
  0.1 Hz) with a perfect gyro. The accelerometer pitch is off by atan(a/g) while the axle
  accelerates; the faster the bias tracking, the more of it reaches the pitch;
* the RMS pitch error under test_imu_filter's harsh profile (3 m/s^2 at 0.7 Hz, limit 5 mrad).
The filter without bias tracking (bias noise 1e-20) is printed and drawn for reference.
"""

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import NullLocator

from krang_can_bridge.config import load_devices
from krang_can_bridge.imu_filter import ImuPitchEstimator, pitch_axis, sensor_vectors
from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_sim.closed_loop import ClosedLoop
from krang_sim.scenarios import TABLE2_POSE
from krang_sim.sensors import SensorModel, device_scales

DT = 0.005  # sim_krang's DMU sample period
RATE_LSB, ACCEL_LSB = device_scales().gyro_lsb_rad_s, device_scales().accel_lsb_m_s2  # the DBC's
BIAS = 0.01  # rad/s, the unannounced gyro-bias step
STEP_AT = 10.0  # s
SETTLE = 120.0  # s after the step where the "steady" error is read


def imu_with(bias_process_noise, imu=None):
    imu = imu or load_devices().imu
    kalman = dataclasses.replace(imu.kalman, bias_process_noise=bias_process_noise)
    return dataclasses.replace(imu, kalman=kalman)


def feed(imu, pitch, rate, accel, bias):
    """(pitch error [rad], bias estimate [rad/s]) of the estimator over a trajectory sampled at DT
    (arrays: true pitch, pitch rate, forward axle acceleration, unannounced gyro bias)."""
    est = ImuPitchEstimator(imu)
    axis, known = pitch_axis(imu.mount_angle_rad), np.asarray(imu.gyro_bias_rad_s)
    err, bias_est = np.full(len(pitch), np.nan), np.zeros(len(pitch))
    for k in range(len(pitch)):
        f, w = sensor_vectors(
            pitch[k], rate[k], imu.mount_angle_rad, forward_specific_force=accel[k]
        )
        w = np.round((w + known + bias[k] * axis) / RATE_LSB) * RATE_LSB
        f = np.round(f / ACCEL_LSB) * ACCEL_LSB
        e = est.update(w, f, k * DT)
        if e.ready:
            err[k], bias_est[k] = e.pitch - pitch[k], est.filter.bias
    return err, bias_est


def sitting(imu):
    """(tracking time constant [s], max |error| 90-120 s after the bias step [rad], peak |error|
    after the step [rad]) for a robot still on its caster."""
    n = int((STEP_AT + SETTLE) / DT) + 1
    t = np.arange(n) * DT
    bias = np.where(t >= STEP_AT, BIAS, 0.0)
    sitting_pitch = drivetrain(load_krang()).caster_pitch
    err, b = feed(imu, np.full(n, sitting_pitch), np.zeros(n), np.zeros(n), bias)
    after = t >= STEP_AT
    reached = np.nonzero(after & (b >= (1 - math.exp(-1)) * BIAS))[0]
    tau = t[reached[0]] - STEP_AT if len(reached) else math.inf
    late = t >= t[-1] - 30.0
    return tau, float(np.max(np.abs(err[late]))), float(np.nanmax(np.abs(err[after])))


def balancing_trajectory(seconds=100.0, amplitude=0.1, freq=0.1, move_from=20.0):
    """True (pitch, rate, axle acceleration) at the DMU's sample times from the closed loop, and
    the mask of the moving part: the robot comes to rest on its caster (1 s: the bridge starts on
    a resting robot), sits 1 s, stands up, balances, and from `move_from` s its position
    reference moves +-`amplitude` m at `freq` Hz."""
    robot = load_krang()
    beta = load_beta(config_path('sim_true_beta.yaml'), robot)
    loop = ClosedLoop(robot, beta, beta, TABLE2_POSE, seed=0)
    ctl, plant = loop.controller, loop.plant
    dmu = SensorModel(robot)  # what the DMU is given of the motion (no misalignment)
    rows, x0 = [], None
    loop.run(1.0)
    while plant.t < seconds:
        if not ctl.enabled and plant.t >= 2.0:
            ctl.set_enabled(True)
        loop.run(loop.h)
        if plant.t > move_from and ctl.mode.value == 'balance':
            x0 = ctl.x_ref if x0 is None else x0
            ctl.x_ref = x0 + amplitude * math.sin(2 * math.pi * freq * (plant.t - move_from))
        pitch, rate, forward, _ = dmu.dmu_inputs(plant.motion())
        rows.append((plant.t, pitch, rate, forward))
    if ctl.mode.value != 'balance':
        raise RuntimeError('the closed loop did not balance')
    t, pitch, rate, accel = np.array(rows).T
    grid = np.arange(t[0], t[-1], DT)
    return (*(np.interp(grid, t, v) for v in (pitch, rate, accel)), grid >= move_from)


def balancing(imu, traj):
    """Peak |pitch error| [rad] while the robot moves (perfect gyro)."""
    pitch, rate, accel, moving = traj
    err, _ = feed(imu, pitch, rate, accel, np.zeros(len(pitch)))
    return float(np.max(np.abs(err[moving])))


def harsh(imu, seconds=40.0):
    """RMS pitch error [rad] under test_imu_filter's profile, after a still start-up of 2 s."""
    w = 2 * math.pi * 0.4
    t = np.arange(int((seconds + 2.0) / DT)) * DT - 2.0
    moving = t >= 0.0
    pitch = np.where(moving, -1.55 + 0.08 * np.sin(w * t), -1.55)
    rate = np.where(moving, 0.08 * w * np.cos(w * t), 0.0)
    accel = np.where(moving, 3.0 * np.sin(2 * math.pi * 0.7 * t + 1.0), 0.0)
    err, _ = feed(imu, pitch, rate, accel, np.zeros(len(t)))
    return float(np.sqrt(np.mean(err[t > 10.0] ** 2)))


def plot(out, rows, chosen, reference):
    q, tau, steady, peak, bal, hr = (np.array(c) for c in zip(*rows))
    fig = Figure(figsize=(9, 7.2))
    ax = fig.subplots()
    ax.loglog(
        q,
        steady * 1e3,
        'o-',
        color='C0',
        label=f'sitting: max |pitch error| 90-120 s '
        f'after an unannounced {BIAS} rad/s gyro-bias step',
    )
    ax.loglog(
        q,
        peak * 1e3,
        's:',
        color='C0',
        alpha=0.6,
        label='sitting: peak |pitch error| after that step',
    )
    ax.loglog(
        q,
        bal * 1e3,
        '^-',
        color='C1',
        label='balancing (closed loop, +-10 cm at 0.1 Hz, perfect gyro): peak |pitch error|',
    )
    ax.loglog(
        q, hr * 1e3, 'v-', color='C2', label='harsh profile (3 m/s^2 at 0.7 Hz): RMS pitch error'
    )
    ax.axhline(2.0, color='k', ls='--', lw=1, label='requirement: steady error <= 2 mrad')
    ax.axhline(
        5.0, color='C2', ls='--', lw=1, label='harsh-profile limit of test_imu_filter: 5 mrad RMS'
    )
    ax.axhline(
        reference[0] * 1e3,
        color='C3',
        ls='-.',
        lw=1,
        label='no bias tracking: max |pitch error| 90-120 s after the step',
    )
    ax.axhline(
        reference[1] * 1e3,
        color='C1',
        ls='-.',
        lw=1,
        label='no bias tracking: balancing peak |pitch error|',
    )
    ax.axvline(
        chosen,
        color='C4',
        lw=3,
        alpha=0.4,
        label=f'configured imu.kalman.bias_process_noise = {chosen:.0e}',
    )
    ax.set_xlabel('bias process noise, imu.kalman.bias_process_noise [(rad/s)^2/s]')
    ax.set_ylabel('pitch error [mrad]')
    top = ax.secondary_xaxis('top')
    top.set_xticks(q[::2], [f'{x:.0f}' for x in tau[::2]])
    top.xaxis.set_minor_locator(NullLocator())
    top.set_xlabel('bias tracking time constant [s] (63 % of a step)')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=7.5, loc='upper center', bbox_to_anchor=(0.5, -0.1), ncol=2)
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument(
        '--out',
        default=str(Path(__file__).resolve().parents[1] / 'docs' / 'imu_bias_tradeoff.png'),
    )
    args = ap.parse_args(argv)
    base = load_devices().imu
    chosen = base.kalman.bias_process_noise
    sweep = [q for q in np.logspace(-10, -6, 9) if abs(math.log(q / chosen)) > 0.2]
    sweep = sorted(sweep + [chosen])
    traj = balancing_trajectory()
    print(f'balancing: peak axle acceleration {np.max(np.abs(traj[2][traj[3]])):.2f} m/s^2')
    print(
        f'{"bias noise":>11} {"tau [s]":>8} {"90-120 s":>9} {"peak":>7} {"balancing":>10} '
        f'{"harsh rms":>9}   (errors in mrad)'
    )
    rows = []
    for q in sweep:
        imu = imu_with(q, base)
        tau, steady, peak = sitting(imu)
        bal, hr = balancing(imu, traj), harsh(imu)
        rows.append((q, tau, steady, peak, bal, hr))
        print(
            f'{q:11.1e} {tau:8.1f} {steady * 1e3:9.2f} {peak * 1e3:7.1f} {bal * 1e3:10.2f} '
            f'{hr * 1e3:9.2f}' + ('  <- configured' if q == chosen else '')
        )
    off = imu_with(1e-20, base)
    reference = sitting(off)[1], balancing(off, traj)
    print(
        f'no bias tracking: {reference[0] * 1e3:.1f} mrad 90-120 s after the step, balancing '
        f'peak {reference[1] * 1e3:.2f} mrad, harsh rms {harsh(off) * 1e3:.2f} mrad'
    )
    plot(args.out, rows, chosen, reference)
    print(f'wrote {args.out}')


if __name__ == '__main__':
    main()
