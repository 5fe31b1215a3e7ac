"""Closed-loop simulation without ROS: the true robot (``KrangSim`` with the hidden beta) under the
``BalanceController`` (estimated beta), with sensor noise and quantisation, actuator limits, the
controller at its own rate (500 Hz) and the physics at 1 kHz.

* ``ClosedLoop``: one simulated robot + controller; ``run(seconds)`` advances both and logs.
* ``run_balance``: sit -> stand up -> balance for T seconds; returns a ``metrics.BalancingRun``
  (currents, x_wheel_rad, dx_wheel_rad_s, theta, ...) logged at the hardware's 30 Hz, so the
  paper's Table II definitions (20-sample smoothing, mJ-per-step "power") mean what they meant.
* ``run_online_session``: the online learning loop: command a pose (a fixed list, or a chooser
  such as krang_pose_server.selection.AdaptiveSelector asked with the learner's posterior), move
  there as the pose server does (a straight line streamed at 20 Hz by the pose server's own
  ``MoveStreamer``, held while the controller's balance_converged is false), keep balancing while
  the joints move, wait for the detector's point, update beta with the learner (with the point's
  standard error), push it into the controller, repeat.
  The learner is any estimator of the registry (krang_com_estimator.estimators.make_estimator;
  default the paper's GD, ``paper-gd``): ``update(q_base, joints)``, then ``beta``.

Speed. ``FastKrangSim`` is a ``KrangSim`` whose hot path (joints still, no actuation delay) calls
``WipDynamics.step`` directly and draws the sensor noise in blocks, and ``control_sample()`` builds
the controller's sample straight from the state with the noise model of ``KrangSim.sensors``
(pitch, gyro-rate quantisation, encoder counts, joint noise; the gyro vector and accelerometer,
which the controller does not read, are skipped). With zero noise it equals
``sample_from_sensors(sensors())`` exactly, and stepping equals ``KrangSim.step`` exactly
(test_closed_loop.py). While joints move, it falls back to ``KrangSim.step`` (which re-reduces the
pose every 20 ms).
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from krang_adrc_controller.controller import (
    BalanceController,
    ControlSample,
    ControllerConfig,
    load_controller_config,
)
from krang_adrc_controller.metrics import BalancingRun
from krang_com_estimator.estimators import make_estimator
from krang_model.com import balance_pitch
from krang_pose_server.sequence import StraightLineMove
from krang_pose_server.streaming import MoveStreamer, PauseConfig

from .physics import KrangSim, SimConfig

#: The upper-body pose of the paper's Table II runs (first row of balancing_runs/table2/*.csv).
TABLE2_POSE = np.array(
    [
        2.75467,
        0.0749392,
        1.00799,
        -1.113,
        -0.000251086,
        -1.59399,
        0.0370958,
        1.02202,
        -0.0209895,
        -0.854931,
        1.113,
        0.000271173,
        1.561,
        -0.0280979,
        -1.052,
        0.0210068,
    ]
)

MODE_CODES = {'safe_stop': -1, 'sit': 0, 'stand_up': 1, 'balance': 2, 'sit_down': 3}


# ----------------------------------------------------------------------------- fast simulated rob


class FastKrangSim(KrangSim):
    """KrangSim with a fast path for the closed loop (see the module docstring)."""

    _BLOCK = 4096

    def __init__(self, robot, true_beta, joints, q_base=None, config=None):
        super().__init__(robot, true_beta, joints, q_base=q_base, config=config)
        self._moving = False
        self._nrow = self._BLOCK
        self._scalars = None
        self._jnoise = None
        n = self.config.noise
        self._half = 0.5 * self.drive.track_width / self.drive.wheel_radius
        self._kt = self.drive.torque_constant * self.drive.gear_ratio  # the true Kt (SimEffects)
        self._jbase = self.joints + self._enc_offset
        self._noise = (
            n.imu_pitch_std_rad,
            n.gyro_std_rad_s,
            n.gyro_lsb_rad_s,
            n.encoder_counts_per_rad,
            n.joint_std_rad,
        )

    def command_joints(self, targets):
        super().command_joints(targets)
        self._moving = self.joints_moving

    def _refill(self):
        rng = self.rng
        self._scalars = rng.standard_normal((self._BLOCK, 2)).tolist()
        self._jnoise = rng.standard_normal((self._BLOCK, len(self.joints))) * self._noise[4]
        self._nrow = 0

    def step(self, n=1):
        """Same as KrangSim.step; fast when the joints are still and there is no actuation
        delay."""
        if self._moving or self.config.effects.actuation_delay_s > 0.0 or self._delay:
            for _ in range(n):
                super().step(1)
                if self._moving and not self.joints_moving:
                    self._moving = False
                    self._jbase = self.joints + self._enc_offset
            if self._moving:
                self._jbase = self.joints + self._enc_offset
            return
        dt = self.config.dt
        lim = self.drive.current_limit
        cl, cr = self._current_cmd
        il = lim if cl > lim else (-lim if cl < -lim else cl)
        ir = lim if cr > lim else (-lim if cr < -lim else cr)
        self.applied_current = (il, ir)
        tl, tr = self._kt * il, self._kt * ir
        dyn = self.dynamics
        state = self.state
        prev = state
        for _ in range(n):
            prev = state
            state = dyn.step(prev, tl, tr, dt)
            self.t += dt
        self.state = state
        self._accel = (
            (state[2] - prev[2]) / dt,
            (state[3] - prev[3]) / dt,
            (state[5] - prev[5]) / dt,
        )

    def control_sample(self) -> ControlSample:
        """The controller's sample now, with the sensor noise model of KrangSim.sensors()."""
        if self._nrow >= self._BLOCK:
            self._refill()
        k = self._nrow
        self._nrow = k + 1
        n0, n1 = self._scalars[k]
        imu_std, gyro_std, lsb, cpr, _ = self._noise
        ph, qb, dph, dqb, psi, _dpsi = self.state
        half = self._half
        rel = ph - qb
        dpsi = _dpsi
        return ControlSample(
            self.t,
            qb + self.config.effects.imu_pitch_bias_rad + imu_std * n0,
            round((dqb + gyro_std * n1) / lsb) * lsb,
            round((rel - half * psi) * cpr) / cpr,
            round((rel + half * psi) * cpr) / cpr,
            dph - dqb - half * dpsi,
            dph - dqb + half * dpsi,
            self._jbase + self._jnoise[k],
            self._moving,
        )


# ----------------------------------------------------------------------------- wrong betas


def shifted_beta(robot, beta, joints, shift_m, q_base=None):
    """`beta` with the Base body's mass moment changed so that, in pose `joints` at pitch `q_base`
    (default: the balance pitch of `beta`), the paper's x_com = phi^T beta moves by `shift_m` (m,
    positive = the model puts the CoM forward of where `beta` has it). A controlled "wrong CoM"."""
    beta = np.array(beta, dtype=float)
    joints = np.asarray(joints, float)
    qb = balance_pitch(robot, joints[None], beta)[0] if q_base is None else float(q_base)
    i = robot.body_names.index('Base')
    # frame-0 x axis in base coordinates is (0, sin q, -cos q) (krang_model.com)
    beta[4 * i + 2] += robot.nominal_mass * shift_m * math.sin(qb)
    beta[4 * i + 3] -= robot.nominal_mass * shift_m * math.cos(qb)
    return beta


# ----------------------------------------------------------------------------- the loop


@dataclass
class Disturbance:
    """An event at time t (s): 'kick' adds `value` rad/s to the body's pitch rate (a push);
    'current' adds `value` A to both wheel currents for `duration` s; 'joints' commands the pose
    `value`; 'dropout' freezes the sensor samples from t on (stale data)."""

    t: float
    kind: str
    value: object = 0.0
    duration: float = 0.0


class ClosedLoop:
    """One simulated Krang (hidden `true_beta`) under a BalanceController (estimated
    `beta_est`)."""

    def __init__(
        self,
        robot,
        true_beta,
        beta_est,
        joints,
        *,
        q_base=None,
        controller_config: ControllerConfig | None = None,
        sim_config: SimConfig | None = None,
        seed: int = 0,
        log_rate_hz: float = 30.0,
    ):
        sim_config = sim_config or SimConfig()
        sim_config = replace(sim_config, seed=seed)
        self.robot = robot
        self.sim = FastKrangSim(robot, true_beta, joints, q_base=q_base, config=sim_config)
        self.controller = BalanceController(
            robot, beta_est, controller_config or load_controller_config()
        )
        self.h = self.controller.h
        ratio = self.h / sim_config.dt
        self.n_sub = int(round(ratio))
        if abs(ratio - self.n_sub) > 1e-9 or self.n_sub < 1:
            raise ValueError('the controller period must be a multiple of the physics step')
        self.log_period = 1.0 / log_rate_hz if log_rate_hz else 0.0
        self._next_log = 0.0
        self.log = {
            k: []
            for k in (
                't',
                'i_left',
                'i_right',
                'x_wheel_rad',
                'x_ref_m',
                'dx_wheel_rad_s',
                'theta_rad',
                'dtheta_rad_s',
                'psi_wheel_rad',
                'dpsi_wheel_rad_s',
                'q_base_rad',
                'q_base_true',
                'x_true_m',
                'balance_pitch_true',
                'mode',
                'f_hat_x',
                'f_hat_theta',
            )
        }
        self.events: list[tuple[float, str]] = []
        self.points = []
        self.disturbances: list[Disturbance] = []
        self._frozen = None
        self._extra_current = (0.0, 0.0, -1.0)  # (left, right, until)
        self.last_output = None
        self.control_steps = 0
        self.streamer: MoveStreamer | None = None  # the pose server's move under way
        self.goal = None  # its goal until the joints reach it (the sample's move_pending)
        self.moves: list[MoveStreamer] = []  # every move streamed, for its pauses
        self._stream = (0.0, 0.0, 0)  # (start, period, ticks sent)
        self._pause_on_flag = True

    def start_move(self, goal, speed_fraction=0.8, rate_hz=20.0, pause=PauseConfig()):
        """Start the pose server's move to `goal` (StraightLineMove from the current joint
        targets, streamed at `rate_hz` by krang_pose_server.streaming.MoveStreamer, paused on the
        controller's balance_converged as `pause` says; None = never pause). rate_hz=0: the goal
        at once (each joint dashes at its own top speed). Returns the planned duration, s."""
        sim = self.sim
        goal = np.asarray(goal, float)
        self.goal = goal
        if not rate_hz:
            sim.command_joints(goal)
            return 0.0
        move = StraightLineMove.plan(
            sim.joint_targets, goal, self.robot.velocity_limit, speed_fraction
        )
        self.streamer = MoveStreamer(move, pause or PauseConfig())
        self._pause_on_flag = pause is not None
        self.moves.append(self.streamer)
        self._stream = (sim.t, 1.0 / rate_hz, 1)
        sim.command_joints(self.streamer.setpoint)
        return move.duration

    def _stream_tick(self, converged):
        """One streamed target, as the pose server's timer sends it."""
        start, period, k = self._stream
        self._stream = (start, period, k + 1)
        st = self.streamer
        event = st.advance(period, converged or not self._pause_on_flag)
        if event is not None:
            self.events.append((self.sim.t, f'move {event}: {st.summary()}'))
        self.sim.command_joints(st.setpoint)
        if st.done:
            self.streamer = None

    def schedule(self, *disturbances: Disturbance):
        self.disturbances.extend(disturbances)
        self.disturbances.sort(key=lambda d: d.t)

    def _apply_disturbances(self):
        t = self.sim.t
        while self.disturbances and self.disturbances[0].t <= t + 1e-12:
            d = self.disturbances.pop(0)
            if d.kind == 'kick':
                self.sim.state[3] += float(d.value)
            elif d.kind == 'current':
                self._extra_current = (float(d.value), float(d.value), t + d.duration)
            elif d.kind == 'joints':
                self.sim.command_joints(np.asarray(d.value, float))
            elif d.kind == 'dropout':
                self._frozen = self.sim.control_sample()
            else:
                raise ValueError(f'unknown disturbance {d.kind!r}')
            self.events.append((t, f'disturbance {d.kind}'))

    def run(self, seconds: float, until=None) -> bool:
        """Advance `seconds`; stop early (returning True) when `until(output)` is true. The cyclic
        garbage collector is paused meanwhile (the loop makes no reference cycles; ~20 % faster).
        """
        enabled = gc.isenabled()
        gc.disable()
        try:
            return self._run(seconds, until)
        finally:
            if enabled:
                gc.enable()

    def _run(self, seconds, until):
        sim, ctl, n_sub = self.sim, self.controller, self.n_sub
        steps = int(round(seconds / self.h))
        log = self.log
        lp = self.log_period
        r = ctl.r
        for _ in range(steps):
            if self.disturbances:
                self._apply_disturbances()
            if self.streamer is not None:
                start, period, k = self._stream
                if sim.t >= start + k * period - 1e-9:
                    last = self.last_output
                    self._stream_tick(last is not None and last.balance_converged)
            sample = self._frozen if self._frozen is not None else sim.control_sample()
            if self.goal is not None:
                if self.streamer is None and not np.any(np.abs(self.goal - sim.joints) > 0.01):
                    self.goal = None
                else:
                    sample.move_pending = True
            out = ctl.step(sample, now=sim.t)
            self.control_steps += 1
            il, ir = out.current_left, out.current_right
            if self._extra_current[2] > sim.t:
                il += self._extra_current[0]
                ir += self._extra_current[1]
            sim.command_currents(il, ir)
            if out.events:
                t = sample.t
                self.events.extend((t, e) for e in out.events)
            if out.balanced_point is not None:
                self.points.append(out.balanced_point)
            if lp and sample.t >= self._next_log - 1e-9:
                self._next_log += lp
                if self._next_log <= sample.t:
                    self._next_log = sample.t + lp
                st = sim.state
                log['t'].append(sample.t)
                log['i_left'].append(out.current_left)
                log['i_right'].append(out.current_right)
                log['x_wheel_rad'].append(out.x / r)
                log['x_ref_m'].append(out.x_ref)
                log['dx_wheel_rad_s'].append(out.dx / r)
                log['theta_rad'].append(out.theta)
                log['dtheta_rad_s'].append(out.dtheta)
                log['psi_wheel_rad'].append(out.psi)
                log['dpsi_wheel_rad_s'].append(
                    0.5 * (sample.wheel_right_rate - sample.wheel_left_rate)
                )
                log['q_base_rad'].append(sample.q_base)
                log['q_base_true'].append(st[1])
                log['x_true_m'].append(sim.drive.wheel_radius * st[0])
                log['balance_pitch_true'].append(-sim.dynamics.body.com_offset_full)
                log['mode'].append(MODE_CODES[out.mode])
                log['f_hat_x'].append(out.f_hat_x)
                log['f_hat_theta'].append(out.f_hat_theta)
            sim.step(n_sub)
            self.last_output = out
            if until is not None and until(out):
                return True
        return False

    def balancing_run(self, name='', source='sim') -> BalancingRun:
        lg = {k: np.asarray(v, float) for k, v in self.log.items()}
        extra = {
            k: lg[k]
            for k in (
                'q_base_true',
                'x_true_m',
                'balance_pitch_true',
                'mode',
                'f_hat_x',
                'f_hat_theta',
            )
        }
        extra['events'] = list(self.events)
        extra['points'] = list(self.points)
        return BalancingRun(
            t=lg['t'],
            i_left=lg['i_left'],
            i_right=lg['i_right'],
            x_wheel_rad=lg['x_wheel_rad'],
            dx_wheel_rad_s=lg['dx_wheel_rad_s'],
            theta_rad=lg['theta_rad'],
            dtheta_rad_s=lg['dtheta_rad_s'],
            psi_wheel_rad=lg['psi_wheel_rad'],
            dpsi_wheel_rad_s=lg['dpsi_wheel_rad_s'],
            q_base_rad=lg['q_base_rad'],
            name=name,
            source=source,
            extra=extra,
        )


def _mode_times(events):
    """{mode: first time entered} from controller events 'a->b: why'."""
    out = {}
    for t, e in events:
        if '->' in e and ':' in e:
            target = e.split('->', 1)[1].split(':', 1)[0]
            out.setdefault(target, t)
    return out


def run_balance(
    robot,
    true_beta,
    beta_est,
    *,
    joints=TABLE2_POSE,
    seconds: float = 60.0,
    enable_at_s: float = 1.0,
    seed: int = 0,
    controller_config: ControllerConfig | None = None,
    sim_config: SimConfig | None = None,
    disturbances=(),
    log_rate_hz: float = 30.0,
    name: str = '',
) -> BalancingRun:
    """Sit on the caster, enable at `enable_at_s` (the controller then stands up when its stand
    guard allows) and balance until `seconds`. Returns a BalancingRun logged at `log_rate_hz`;
    ``extra`` holds the truth (q_base_true, x_true_m, balance_pitch_true), modes, observer outputs,
    events, detector points, 'stood_up' (off the caster and upright for the last 2 s),
    'reached_balance_mode', 'mode_times', 'true_balance_pitch', 'theta_error_rad',
    'expected_rest_offset_m', 'theta_on_caster_model_rad', 'first_stand_current_a' and timings."""
    loop = ClosedLoop(
        robot,
        true_beta,
        beta_est,
        joints,
        controller_config=controller_config,
        sim_config=sim_config,
        seed=seed,
        log_rate_hz=log_rate_hz,
    )
    loop.schedule(*disturbances)
    wall = time.perf_counter()
    loop.run(enable_at_s)
    loop.controller.set_enabled(True)
    loop.run(seconds - enable_at_s)
    wall = time.perf_counter() - wall
    run = loop.balancing_run(name=name)
    times = _mode_times(loop.events)
    ctl = loop.controller
    # stood up = off the caster and upright (within 0.1 rad of the true balance pitch) over the
    # last 2 s, under STAND_UP or BALANCE control (a controller may balance in its stand-up mode,
    # as in 2018)
    last = run.t >= run.t[-1] - 2.0
    upright = bool(
        np.all(
            np.abs(run.extra['q_base_true'][last] - run.extra['balance_pitch_true'][last]) < 0.1
        )
    )
    stood = upright and ctl.mode.value in ('stand_up', 'balance') and 'stand_up' in times
    i_first = next(
        (float(i) for i, m in zip(run.i_left, run.extra['mode']) if m == MODE_CODES['stand_up']),
        math.nan,
    )
    run.extra.update(
        stood_up=stood,
        reached_balance_mode='balance' in times,
        mode_times=times,
        final_mode=ctl.mode.value,
        first_stand_current_a=i_first,
        theta_on_caster_model_rad=loop.sim.drive.caster_pitch + ctl.com_offset,
        true_balance_pitch=loop.sim.balance_pitch(),
        theta_error_rad=ctl.com_offset + loop.sim.balance_pitch(),
        expected_rest_offset_m=(
            ctl.expected_rest_offset() * (ctl.com_offset + loop.sim.balance_pitch())
            if ctl.design
            else math.nan
        ),
        wall_s=wall,
        sim_s=seconds,
        control_steps=loop.control_steps,
        seed=seed,
    )
    run.extra['loop'] = loop
    return run


@dataclass
class SessionResult:
    betas: np.ndarray  # (k + 1, n_beta): beta_0 and after each update
    points: list  # BalancedPoint per learned pose
    pose_indices: list  # index into `poses` of each point
    timings: list  # per pose: dict(move_s, settle_s, total_s, ok)
    true_pitch: list  # true balance pitch of each learned pose
    stood_up_s: float
    sim_s: float
    wall_s: float
    failures: list = field(default_factory=list)
    loop: object = None
    poses: np.ndarray = None  # the commanded poses (the chooser's picks, if adaptive)

    @property
    def beta(self):
        return self.betas[-1]


def stand_pose(
    robot,
    beta_est,
    base=TABLE2_POSE,
    target_theta_rad=-6.0 * math.pi / 180.0,
    caster_pitch=None,
    waist_range=(1.5, 2.88),
):
    """`base` with the waist set so that, sitting on the caster, the CoM angle the ESTIMATED beta
    predicts is `target_theta_rad` (the middle of the stand window): a pose the controller agrees
    to stand up in. Uses only the estimate (as an operator would). Bisection; theta on the caster
    decreases as the waist opens."""
    from krang_model.drivetrain import drivetrain

    caster = drivetrain(robot).caster_pitch if caster_pitch is None else caster_pitch
    base = np.array(base, dtype=float)

    def theta_sit(w):
        p = base.copy()
        p[0] = w
        return caster - balance_pitch(robot, p[None], beta_est)[0]

    lo, hi = waist_range
    if not theta_sit(lo) <= target_theta_rad <= theta_sit(hi):
        return base
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if theta_sit(mid) < target_theta_rad:
            lo = mid
        else:
            hi = mid
    out = base.copy()
    out[0] = 0.5 * (lo + hi)
    return out


def run_online_session(
    robot,
    true_beta,
    beta0,
    poses,
    learner=None,
    *,
    start_pose=None,
    seed: int = 0,
    controller_config: ControllerConfig | None = None,
    sim_config: SimConfig | None = None,
    pose_timeout_s: float = 90.0,
    stand_timeout_s: float = 30.0,
    progress: bool = True,
    log_rate_hz: float = 0.0,
    speed_fraction: float = 0.8,
    stream_rate_hz: float = 20.0,
    pause: PauseConfig | None = PauseConfig(),
    n_poses: int | None = None,
) -> SessionResult:
    """Stand up in `start_pose` (default: ``stand_pose(robot, beta0)``, the Table II pose with the
    waist set so that beta0 agrees to stand up), then for each pose (rows of joints, pose order):
    command it, balance while the joints move, wait for the detector's point,
    ``learner.update(q_base, joints)``, ``controller.set_beta(learner.beta)``. `learner`: an
    estimator of the registry, by default ``make_estimator('paper-gd', robot, beta0)``. A pose
    without a point within `pose_timeout_s` is skipped (listed in failures); if the robot leaves
    BALANCE the session ends there.

    `poses` is a fixed list, or a chooser with ``choose(beta, covariance, current_joints)``
    returning an object with ``joints`` (krang_pose_server.selection.AdaptiveSelector), asked
    before each of `n_poses` moves with the learner's current posterior. Each move is the pose
    server's streamed straight line (`speed_fraction` of the joint speed limits, targets at
    `stream_rate_hz`), held while the controller's balance_converged is false as `pause` says
    (``ClosedLoop.start_move``; None = never pause)."""
    adaptive = not isinstance(poses, (np.ndarray, list, tuple))
    if adaptive:
        chooser, poses = poses, [None] * int(n_poses)
    else:
        poses = np.atleast_2d(np.asarray(poses, float))
    learner = learner if learner is not None else make_estimator('paper-gd', robot, beta0)
    if start_pose is None:
        start_pose = stand_pose(robot, learner.beta)
    loop = ClosedLoop(
        robot,
        true_beta,
        beta0,
        start_pose,
        controller_config=controller_config,
        sim_config=sim_config,
        seed=seed,
        log_rate_hz=log_rate_hz,
    )
    ctl = loop.controller
    if np.any(np.asarray(learner.beta) != np.asarray(beta0)):
        ctl.set_beta(learner.beta)
    wall = time.perf_counter()
    loop.run(0.5)
    ctl.set_enabled(True)
    ok = loop.run(stand_timeout_s, until=lambda o: o.mode == 'balance')
    if not ok:
        raise RuntimeError(
            f'online session: the robot did not stand up within {stand_timeout_s} s '
            f'(mode {ctl.mode.value}; events {loop.events[-3:]})'
        )
    stood = loop.sim.t
    betas = [np.array(learner.beta, float)]
    points, idx, timings, true_pitch, failures, chosen = [], [], [], [], [], []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(poses), desc='online session', unit='pose', leave=False)
    try:
        for i, pose in enumerate(poses):
            if adaptive:
                choice = chooser.choose(learner.beta, learner.covariance, loop.sim.joint_targets)
                if choice is None:
                    break
                pose = choice.joints
                chosen.append(pose)
            t0 = loop.sim.t
            loop.start_move(pose, speed_fraction, stream_rate_hz, pause)
            moved = [None]

            def done(o, moved=moved):
                if moved[0] is None and loop.streamer is None and not loop.sim._moving:
                    moved[0] = loop.sim.t
                return o.balanced_point is not None or o.mode != 'balance'

            got = loop.run(pose_timeout_s, until=done)
            out = loop.last_output
            if out.mode != 'balance':
                failures.append((i, f'left balance: {out.mode}'))
                break
            if not got or out.balanced_point is None:
                failures.append((i, 'no balanced point within the timeout'))
                if bar is not None:
                    bar.update(1)
                continue
            p = out.balanced_point
            true_pitch.append(loop.sim.balance_pitch())
            if p.q_base_se > 0:  # the detector's standard error, as /balanced_pose carries it
                learner.update(p.q_base, p.joints, sigma=p.q_base_se)
            else:
                learner.update(p.q_base, p.joints)
            beta = learner.beta
            ctl.set_beta(beta)
            betas.append(np.array(beta, float))
            points.append(p)
            idx.append(i)
            t1 = loop.sim.t
            mv = (moved[0] if moved[0] is not None else t1) - t0
            paused = loop.moves[-1].paused_s if loop.moves and stream_rate_hz else 0.0
            timings.append(
                {
                    'move_s': mv,
                    'settle_s': t1 - t0 - mv,
                    'total_s': t1 - t0,
                    'paused_s': paused,
                    'ok': True,
                }
            )
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - wall
    return SessionResult(
        np.array(betas),
        points,
        idx,
        timings,
        true_pitch,
        stood,
        loop.sim.t,
        wall,
        failures,
        loop,
        np.array(chosen) if adaptive else poses,
    )
