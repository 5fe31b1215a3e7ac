"""Synthetic records: the simulated Krang under the ADRC controller, with hidden effects.

``simulate_record`` makes a record with ``KrangSim`` and the ADRC ``BalanceController`` (sit ->
stand up -> balance, pose changes, a current excitation), with hidden ``SimEffects``; the record
it returns carries no trace of those effects.
"""

from __future__ import annotations

import math

import numpy as np

from krang_adrc_controller.controller import BalanceController, ControllerConfig
from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.robot import load_krang
from krang_sim.closed_loop import TABLE2_POSE, FastKrangSim
from krang_sim.physics import SensorNoise, SimConfig, SimEffects

from .record import Record, resample


#: a default pose programme for simulate_record: joint deltas (rad) from the start pose, in
#: pose order (JWaist, JTorso, LJ1..LJFT, RJ1..RJFT); each held for a few seconds in turn
DEFAULT_POSE_PROGRAMME = (
    {'LJ1': 0.6, 'LJ2': 0.5, 'JWaist': -0.12},
    {'RJ1': -0.6, 'RJ2': -0.5, 'JTorso': 0.5, 'LJ4': 0.6},
    {'JWaist': -0.25, 'LJ2': -0.4, 'RJ4': -0.6},
    {},
)


def simulate_record(
    effects=None,
    *,
    seconds: float = 30.0,
    seed: int = 0,
    start_pose=None,
    programme=DEFAULT_POSE_PROGRAMME,
    hold_s: float = 3.0,
    excitation_a: float = 3.0,
    noise=None,
    log_rate_hz: float | None = None,
    sit_down: bool | None = None,
    controller_config=None,
    true_beta=None,
    name: str = 'sim',
) -> Record:
    """A measured-looking record from the simulated Krang (krang_sim.physics) under the ADRC
    BalanceController with the NOMINAL model, with hidden ``effects`` (a SimEffects) in the plant.

    Sequence: sit on the caster for 1 s, enable (stand up, then balance), after 1.5 s of balance go
    through ``programme`` (pose changes, each held ``hold_s``), with a random +-``excitation_a`` A
    telegraph added to both wheel currents while balancing; if ``sit_down`` (default: records of
    20 s or more) return to the start pose and sit down for the last part. The record logs what the
    controller and the hardware would: the noisy sensor samples at the controller rate (or
    ``log_rate_hz``) and the commanded currents (controller output + excitation) as wheel torques,
    every control step. Nothing in the record says which effect was hidden."""
    robot = load_krang()
    beta = load_beta(config_path('sim_true_beta.yaml'), robot)
    truth = beta if true_beta is None else np.asarray(true_beta, float)
    pose0 = np.array(TABLE2_POSE if start_pose is None else start_pose, float)
    sim = FastKrangSim(
        robot,
        truth,
        pose0,
        config=SimConfig(effects=effects or SimEffects(), noise=noise or SensorNoise(), seed=seed),
    )
    # the dataclass defaults, not config/controller.yaml: test data must not change when the
    # deployed controller is retuned. The paper's law, as on the hardware runs (no balance-point
    # observer).
    paper_law = ControllerConfig().override({'balance_point.enabled': False})
    ctl = BalanceController(robot, beta, controller_config or paper_law)
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
                next_pose_t = (
                    t + hold_s + float(np.max(np.abs(target - sim.joints) / robot.velocity_limit))
                )
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
        meas = dict(
            t=grid,
            q_base=pick(log['q']),
            pitch_rate=pick(log['r']),
            wheel=pick(log['w']),
            wheel_rate=pick(log['wr']),
            joints=resample(t, joints, grid),
        )
    else:
        meas = dict(
            t=t,
            q_base=log['q'],
            pitch_rate=log['r'],
            wheel=log['w'],
            wheel_rate=log['wr'],
            joints=joints,
        )
    return Record(
        **meas,
        cmd_t=t,
        cmd_torque=cmd,
        torque_limit=ctl.drive.current_limit * k_motor,
        name=name,
        source='krang_sim',
        kind='sim',
        meta={
            'controller_rate_hz': 1.0 / ctl.h,
            'mode': log['mode'],
            'mode_t': t.copy(),
            'seconds': seconds,
            'seed': seed,
            'stood_up_s': t_balance,
        },
    )
