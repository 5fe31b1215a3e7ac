"""Closed-loop simulation without ROS: a plant (``krang_sim.plant``, any registered engine, with
the hidden beta and the true robot's ``ModelTerms``) under the ``BalanceController`` (estimated
beta), through the one sensor model (``krang_sim.sensors``: noise, quantisation, IMU bias, encoder
offsets), with the controller at its own rate (500 Hz) and the physics at 1 kHz.

``ClosedLoop``: one simulated robot + controller; ``run(seconds)`` advances both and logs. The
pose server's streamed moves and scheduled disturbances act on it; the scenarios built on it
(stand-up-and-balance runs, the online learning session, the Table II runs) are in
``krang_sim.scenarios``. The loop reads the simulator's truth only through ``plant.truth()`` (for
its log), never for control.
"""

from __future__ import annotations

import gc
from dataclasses import dataclass
from functools import partial

import numpy as np

from krang_adrc_controller.controller import (
    BalanceController,
    ControlSample,
    ControllerConfig,
    load_controller_config,
)
from krang_adrc_controller.metrics import BalancingRun
from krang_adrc_controller.modes import MODE_CODES
from krang_model.drivetrain import drivetrain
from krang_model.effects import ModelTerms
from krang_model.com import balance_pitch
from krang_pose_server.sequence import MAX_BALANCE_RATE_RAD_S, StraightLineMove
from krang_pose_server.stand_pose import restand_pose
from krang_pose_server.streaming import MoveStreamer, PauseConfig

from .plant import Plant, make_plant
from .sensors import SensorModel, SensorNoise

#: the columns of ``ClosedLoop.log`` (``*_true``, ``x_true_m``: the plant's truth)
LOG_COLUMNS = (
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
    `beta_est`).

    `plant`: a registered plant's name (``make_plant``) or a ``Plant`` built by the caller;
    `terms`: the true robot's ``ModelTerms`` (None: nominal), for the plant (when it is built
    here) and for the sensor model (IMU bias, encoder offsets); `noise`: the sensors'
    ``SensorNoise`` (None: the hardware's); `plant_options`: more keywords of the plant.

    `restand`: the pose server's re-pose after a caught stand-up (``restand_pose``, its
    ``repose_after_caught_stand`` parameter).

    Hooks for scenarios (None: none): ``sample_hook(sample) -> sample`` sees each sample before
    the controller; ``command_hook(t, sample, output, (il, ir)) -> (il, ir)`` may change the
    currents sent to the drives, after the controller and the scheduled disturbances."""

    def __init__(
        self,
        robot,
        true_beta,
        beta_est,
        joints,
        *,
        q_base=None,
        controller_config: ControllerConfig | None = None,
        plant: str | Plant = 'reduced',
        terms: ModelTerms | None = None,
        noise: SensorNoise | None = None,
        dt: float = 1e-3,
        seed: int = 0,
        log_rate_hz: float = 30.0,
        plant_options: dict | None = None,
        restand: bool = True,
    ):
        self.robot = robot
        terms = terms if terms is not None else ModelTerms.nominal(drivetrain(robot))
        self.terms = terms
        if isinstance(plant, str):
            plant = make_plant(
                plant,
                robot,
                true_beta,
                joints,
                q_base=q_base,
                terms=terms,
                dt=dt,
                **(plant_options or {}),
            )
        self.plant = plant
        self.sensors = SensorModel(robot, terms, noise, seed=seed)
        self.controller = BalanceController(
            robot, beta_est, controller_config or load_controller_config()
        )
        self.h = self.controller.h
        ratio = self.h / plant.dt
        self.n_sub = int(round(ratio))
        if abs(ratio - self.n_sub) > 1e-9 or self.n_sub < 1:
            raise ValueError('the controller period must be a multiple of the physics step')
        self.log_period = 1.0 / log_rate_hz if log_rate_hz else 0.0
        self._next_log = 0.0
        self.log = {k: [] for k in LOG_COLUMNS}
        self.events: list[tuple[float, str]] = []
        self.points = []
        self.move_points = []  # points read on the moves (the controller's move_points)
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
        self.restand = restand
        self._caught = 0  # the controller's caught stand-up tries the pose server has seen
        self.sample_hook = None
        self.command_hook = None

    @property
    def sim(self) -> Plant:
        """The plant (the name the experiments and tests read it by)."""
        return self.plant

    def control_sample(self) -> ControlSample:
        """The controller's sample of the plant now (the sensor model's fast path)."""
        return self.sensors.control_sample(self.plant)

    def start_move(
        self,
        goal,
        speed_fraction=0.8,
        rate_hz=20.0,
        pause=PauseConfig(),
        max_balance_rate=MAX_BALANCE_RATE_RAD_S,
    ):
        """Start the pose server's move to `goal` (StraightLineMove from the current joint
        targets, its pace set by the joints' speed and by the balance pitch the controller's beta
        predicts, streamed at `rate_hz` by krang_pose_server.streaming.MoveStreamer, paused on the
        controller's balance_converged as `pause` says; None = never pause). rate_hz=0: the goal
        at once (each joint dashes at its own top speed). Returns the planned duration, s."""
        plant = self.plant
        goal = np.asarray(goal, float)
        self.goal = goal
        if not rate_hz:
            plant.command_joints(goal)
            return 0.0
        beta = self.controller.beta
        move = StraightLineMove.plan(
            plant.joint_targets,
            goal,
            self.robot.velocity_limit,
            speed_fraction,
            balance=lambda joints: balance_pitch(self.robot, joints, beta),
            max_balance_rate=max_balance_rate,
        )
        self.streamer = MoveStreamer(move, pause or PauseConfig())
        self._pause_on_flag = pause is not None
        self.moves.append(self.streamer)
        self._stream = (plant.t, 1.0 / rate_hz, 1)
        plant.command_joints(self.streamer.setpoint)
        return move.duration

    def _stream_tick(self, converged):
        """One streamed target, as the pose server's timer sends it."""
        start, period, k = self._stream
        self._stream = (start, period, k + 1)
        st = self.streamer
        event = st.advance(period, converged or not self._pause_on_flag)
        if event is not None:
            self.events.append((self.plant.t, f'move {event}: {st.summary()}'))
        self.plant.command_joints(st.setpoint)
        if st.done:
            self.streamer = None

    def _repose(self, com_angle_error):
        """The pose server after a caught stand-up: the waist re-posed by the controller's
        estimate, streamed without pausing (the robot sits)."""
        ctl, joints = self.controller, self.plant.joint_targets
        window = (ctl.modes.stand_error_min, ctl.modes.stand_error_max)
        pose = restand_pose(self.robot, ctl.beta, joints, com_angle_error, window)
        if pose is None or self.streamer is not None:
            return
        self.events.append(
            (
                self.plant.t,
                f'pose server: re-posing the waist {joints[0]:.3f} -> {pose[0]:.3f} rad after a '
                f'caught stand-up (CoM-angle error estimate {com_angle_error:+.4f} rad)',
            )
        )
        self.start_move(pose, pause=None)

    def schedule(self, *disturbances: Disturbance):
        self.disturbances.extend(disturbances)
        self.disturbances.sort(key=lambda d: d.t)

    def _apply_disturbances(self):
        t = self.plant.t
        while self.disturbances and self.disturbances[0].t <= t + 1e-12:
            d = self.disturbances.pop(0)
            if d.kind == 'kick':
                self.plant.push(float(d.value))
            elif d.kind == 'current':
                self._extra_current = (float(d.value), float(d.value), t + d.duration)
            elif d.kind == 'joints':
                self.plant.command_joints(np.asarray(d.value, float))
            elif d.kind == 'dropout':
                self._frozen = self.control_sample()
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
        plant, ctl, n_sub = self.plant, self.controller, self.n_sub
        steps = int(round(seconds / self.h))
        lp = self.log_period
        sample_hook, command_hook = self.sample_hook, self.command_hook
        # the sensor model's fast path, or a caller's replacement of control_sample
        control_sample = self.__dict__.get('control_sample') or partial(
            self.sensors.control_sample, plant
        )
        for _ in range(steps):
            if self.disturbances:
                self._apply_disturbances()
            if self.streamer is not None:
                start, period, k = self._stream
                if plant.t >= start + k * period - 1e-9:
                    last = self.last_output
                    self._stream_tick(last is not None and last.balance_converged)
            sample = self._frozen if self._frozen is not None else control_sample()
            if sample_hook is not None:
                sample = sample_hook(sample)
            if self.goal is not None:
                if self.streamer is None and not np.any(np.abs(self.goal - plant.joints) > 0.01):
                    self.goal = None
                else:
                    sample.move_pending = True
            out = ctl.step(sample, now=plant.t)
            self.control_steps += 1
            if self.restand:
                est = ctl.stand_estimate()
                if (0 if est is None else est[0]) != self._caught:
                    self._caught = 0 if est is None else est[0]
                    if est is not None:
                        self._repose(est[1])
            il, ir = out.current_left, out.current_right
            if self._extra_current[2] > plant.t:
                il += self._extra_current[0]
                ir += self._extra_current[1]
            if command_hook is not None:
                il, ir = command_hook(plant.t, sample, out, (il, ir))
            plant.command_currents(il, ir)
            if out.events:
                t = sample.t
                self.events.extend((t, e) for e in out.events)
            if out.balanced_point is not None:
                self.points.append(out.balanced_point)
            if out.move_points:
                self.move_points.extend(out.move_points)
            if lp and sample.t >= self._next_log - 1e-9:
                self._next_log += lp
                if self._next_log <= sample.t:
                    self._next_log = sample.t + lp
                self._log(sample, out)
            plant.step(n_sub)
            self.last_output = out
            if until is not None and until(out):
                return True
        return False

    def _log(self, sample, out):
        log, r = self.log, self.controller.r
        truth = self.plant.truth()
        log['t'].append(sample.t)
        log['i_left'].append(out.current_left)
        log['i_right'].append(out.current_right)
        log['x_wheel_rad'].append(out.x / r)
        log['x_ref_m'].append(out.x_ref)
        log['dx_wheel_rad_s'].append(out.dx / r)
        log['theta_rad'].append(out.theta)
        log['dtheta_rad_s'].append(out.dtheta)
        log['psi_wheel_rad'].append(out.psi)
        log['dpsi_wheel_rad_s'].append(0.5 * (sample.wheel_right_rate - sample.wheel_left_rate))
        log['q_base_rad'].append(sample.q_base)
        log['q_base_true'].append(truth.q_base)
        log['x_true_m'].append(truth.x_m)
        log['balance_pitch_true'].append(truth.balance_pitch)
        log['mode'].append(MODE_CODES[out.mode])
        log['f_hat_x'].append(out.f_hat_x)
        log['f_hat_theta'].append(out.f_hat_theta)

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
