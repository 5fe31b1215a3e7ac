"""The balancing controller as one object: sit -> stand up -> balance (ADRC on LQR(q)), safe stop,
and the balanced-pose detector. Pure Python, no rclpy; used by the offline closed loop
(``krang_sim.closed_loop``) and by the ROS node. Its inputs and outputs are in ``samples``, the
operator's requests in ``requests.OperatorRequests`` and the model of the held pose in
``design.PoseDesign`` (mixins of ``BalanceController``).

One ``step(sample)`` per control period, in stages:

1. **State.** ``theta`` = CoM angle from vertical of the WHOLE robot (wheels included) computed
   from
   the IMU pitch, the joint encoders and the ESTIMATED beta, as the hardware did
   (``theta = q_base + com_offset_full(joints, beta)``, krang_model.wip). ``x = r (mean(wheel
   encoders) + q_base)`` in metres (the ground-referenced wheel angle, krang_model/README.md),
   ``dx`` likewise from the wheel rates and the pitch rate, ``dtheta`` = IMU pitch rate,
   ``psi = (right - left) / 2`` wheel radians (spin).
2. **Safety** (``_safety``): a runaway speed or a stand-up that does not settle requests a stop.
3. **Modes** (``_mode``, ``modes.ModeMachine``): SIT (ground PD), STAND_UP (the hardware's stand
   PD, in A per wheel radian), BALANCE (ADRC), SIT_DOWN, SAFE_STOP (zero torque; on a stop request,
   a disable, stale or non-finite data). While enabled and sitting, a stand request is issued every
   step (``modes.auto_stand``), refused by the mode machine when theta is outside the stand window.
4. **Balance law** (``_balance_law``): ``adrc.AdrcController`` (the paper's law with the authors'
   ESO input) on LQR(q) through ``lqr.GainCache`` on ``wip.linearize(wip.reduce_pose(pose,
   beta))``, redone only when the pose or beta changes: a settled pose is compared with its
   reference every ``lqr.pose_check_period_s``; while the joints move, the CoM offset is refreshed
   every ``lqr.pose_update_period_s`` and the LQR every ``lqr.gain_update_period_s`` (both again
   when motion stops). The drive chain's torque error the balance-point observer separates from
   the CoM error (its drive observer) is cancelled on both wheels. The spin PD of the hardware's
   BalLo mode is added per wheel. The
   balanced-pose detector (``detector.BalancedPoseDetector``) is fed at ``detector.rate_hz`` with
   the measured q_base, the pitch rate, the ground speed (m/s) and the theta-ESO's f_hat (rad/s^2;
   its noise does not depend on the pose, unlike the compensation torque's). It returns one point
   per settled pose: the window means of all joints and of the measured q_base.
5. **Ground law** (``_ground_law``): the PD of SIT, STAND_UP and SIT_DOWN.
6. **Clamping** (``_clamp``): each wheel's current to the drive train's limit.

Notes. With the authors' ESO input alone the ADRC comes to rest where plain LQR does,
x - x_ref = -F_theta0 delta / F_x0 (delta = theta error of the beta), with the TRUE CoM over the
axle (adrc.py). The balance-point observer (balance_point.py) estimates delta and the ADRC
regulates theta - delta_hat, so the robot rests at x_ref. Either rest is what the detector needs:
its q_base is the true balance pitch whatever the beta. ``rezero_x_on_balance`` (default off)
reproduces the 2018 code's reset of the x reference at every mode change; off, the ADRC keeps the
stand-up's reference, except where the balance-point observer watched the stand-up: BALANCE then
starts at its estimate, where the robot stands, as the 2018 code did (stand.py, "Hand over").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from krang_model.config import config_path
from krang_model.drivetrain import drivetrain
from krang_core import params

from .adrc import AdrcConfig, AdrcController
from .balance_point import ObserverConfig
from .caster import CasterContact
from .design import PoseDesign
from .detector import BalancedPoint, BalancedPoseDetector, DetectorConfig
from .lqr import GainCache, LqrConfig, LqrDesigner
from .modes import Mode, ModeInputs, ModeMachine, ModesConfig, SafetyConfig
from .move_points import MovePointConfig, MovePoints
from .requests import OperatorRequests
from .samples import ControlOutput, ControlSample
from .stand import StandUp

NODE_NAME = 'adrc_controller'


# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class ControllerConfig:
    """Every parameter of the controller, one group per module; the defaults are the shipped
    values. As ROS parameters the names are dotted (``adrc.eso.omega_o``, krang_core/params.py);
    config/controller.yaml and config/sim_params.yaml hold only what differs."""

    rate_hz: float = field(
        default=500.0,
        metadata={'doc': 'control loop rate, Hz; the ESO is discretised at 1/rate_hz'},
    )
    rezero_x_on_balance: bool = field(
        default=False,
        metadata={'doc': "true = the 2018 code's x-reference reset on STAND_UP -> BALANCE"},
    )
    lqr: LqrConfig = LqrConfig()
    adrc: AdrcConfig = AdrcConfig()
    balance_point: ObserverConfig = ObserverConfig()
    modes: ModesConfig = ModesConfig()
    safety: SafetyConfig = SafetyConfig()
    detector: DetectorConfig = DetectorConfig()
    move_points: MovePointConfig = MovePointConfig()

    def __post_init__(self):
        if self.rate_hz <= 0:
            raise ValueError('rate_hz must be positive')
        if self.detector.rate_hz > self.rate_hz:
            raise ValueError('detector.rate_hz must be in (0, rate_hz]')

    def override(self, values: dict) -> 'ControllerConfig':
        """A copy with some dotted parameters changed, e.g. {'balance_point.enabled': False}."""
        return params.override(self, values)


def default_config_path() -> Path:
    return config_path('controller.yaml')


def load_controller_config(path=None, overrides: dict | None = None) -> ControllerConfig:
    """ControllerConfig from a node-parameter YAML (``adrc_controller: ros__parameters: {...}``, or
    a plain mapping; names dotted or nested); default config/controller.yaml. ``overrides`` (dotted
    names) are applied on top."""
    path = Path(path) if path else default_config_path()
    with open(path) as f:
        doc = yaml.safe_load(f) or {}
    if NODE_NAME in doc:
        doc = doc[NODE_NAME] or {}
    if 'ros__parameters' in doc:
        doc = doc['ros__parameters'] or {}
    values = params.nested_to_dotted(doc)
    values.update(overrides or {})
    return params.build(ControllerConfig, values)


# ----------------------------------------------------------------------------- the controller


class BalanceController(OperatorRequests, PoseDesign):
    """See the module docstring. ``robot`` from ``krang_model.robot.load_krang()``."""

    def __init__(self, robot, beta, config: ControllerConfig | None = None):
        self.robot = robot
        self.config = cfg = config if config is not None else load_controller_config()
        self.h = 1.0 / cfg.rate_hz
        # the drive chain as the controller models it: the nominal one, delivering
        # adrc.torque_fraction of its torque per ampere
        nominal = drivetrain(robot)
        self.drive = drive = replace(
            nominal, torque_constant=nominal.torque_constant * cfg.adrc.torque_fraction
        )
        self._ground_scale = 1.0 / cfg.adrc.torque_fraction  # the ground PD's gains are in A
        self.r = drive.wheel_radius
        self.k_motor = drive.torque_constant * drive.gear_ratio  # wheel N m per motor A
        self.designer = LqrDesigner(cfg.lqr, position_unit='m', wheel_radius_m=self.r)
        self.gains = GainCache(self._linearize, self.designer)
        first = Mode.SIT if cfg.modes.start_enabled else Mode.SAFE_STOP
        self.modes = ModeMachine(cfg.modes, cfg.safety, initial_mode=first)
        self.detector = BalancedPoseDetector(cfg.detector)
        self.move_points = MovePoints(cfg.move_points)
        self._detector_every = max(1, int(round(cfg.rate_hz / cfg.detector.rate_hz)))
        self._gravity_pitch = [0.0, 0]  # sum and count since the detector's last feed
        # read by every step: plain attributes, not nested lookups
        self._safety_limits = (cfg.safety.max_speed_m_s, cfg.safety.stand_timeout_s)
        self._spin = (*cfg.modes.spin_gains, cfg.modes.spin_limit_a)
        self._current_limit = drive.current_limit
        # dry friction of the drive chain, added back on each wheel: (current, speed scale)
        self._coulomb = (
            cfg.adrc.coulomb_compensation_nm / self.k_motor,
            cfg.adrc.coulomb_speed_rad_s,
            cfg.adrc.viscous_compensation_nm_s / self.k_motor,
        )
        self._caster = CasterContact(
            drive.caster_pitch + cfg.safety.caster_margin_rad, cfg.safety.caster_catch_s
        )
        self._place = (cfg.balance_point.place_tol_m, cfg.balance_point.place_speed_m_s)
        self._on_caster = False  # caught on the caster in BALANCE or STAND_UP: sit (modes.py)
        self.stand = StandUp(cfg.modes, cfg.safety, drive.caster_pitch, self.h)
        self._stand_gains = [self._ground_scale * g for g in cfg.modes.stand_gains]
        self._pose_check_every = max(1, int(round(cfg.lqr.pose_check_period_s * cfg.rate_hz)))
        self.enabled = bool(cfg.modes.start_enabled)
        self._auto_stand = cfg.modes.auto_stand
        self._stand_once = False  # an operator's stand_up(), consumed in SIT
        # the stand-up under way is the operator's: a caught try re-arms it (stand.py, "Retry")
        self._stand_asked = False
        self._fault: str | None = None  # a drive fault reported by the bridge, latched
        self._stop_requested = False
        self._sit_requested = False
        self._reset_pending = False
        self._steady = False  # no request pending: BALANCE continues (see _requests)
        self._requests()
        self._beta = np.array(beta, dtype=float)
        self._beta_version = 0
        self._body_memo = None
        self._pose = None  # reference pose of the current design
        self._offset = 0.0  # theta = q_base + offset (whole robot, estimated beta)
        self._design = None
        self.adrc: AdrcController | None = None
        self.balance_point = None  # BalancePointObserver when config.balance_point.enabled
        self._balance_point_active = False  # ... and the ADRC regulates about its estimate
        self._moving = False
        self._t_still = -math.inf  # when the joints last stopped
        self._t_balance = -math.inf  # when BALANCE was entered
        self._t_offset = -math.inf
        self._t_gain = -math.inf
        self._t_prev = None
        self._k = 0
        self.x_ref = 0.0
        self.psi_ref = 0.0
        self._refused = False
        self._t_stand = 0.0
        self._sit_from = (0.0, 0.0)  # (t, IMU pitch) at SIT_DOWN entry
        self._stop_reason = None
        self._waist: float | None = None  # of the latest finite sample (the sit guard)
        self.last_output: ControlOutput | None = None
        self.points: list[BalancedPoint] = []
        self.redesigns = 0

    # ------------------------------------------------------------------ public API
    @property
    def beta(self) -> np.ndarray:
        return self._beta.copy()

    @property
    def mode(self) -> Mode:
        return self.modes.mode

    @property
    def com_offset(self) -> float:
        """theta - q_base for the current reference pose and beta (rad)."""
        return self._offset

    @property
    def design(self) -> dict | None:
        """The current LQR(q) design (GainCache dict), None before the first sample."""
        return self._design

    @property
    def stale_timeout_s(self) -> float:
        return self.config.safety.stale_timeout_s

    def stand_estimate(self) -> tuple[int, float] | None:
        """After a caught stand-up (stand.py): (its tries so far, the CoM-angle error it
        estimated, rad, which the next try regulates about and the pose server re-poses by);
        None otherwise (no catch since the last BALANCE)."""
        stand = self.stand
        return (stand.tries, stand.trim) if stand.tries else None

    def set_beta(self, beta) -> None:
        """New estimate: the CoM reference (theta offset) and LQR(q) follow at once."""
        beta = np.array(beta, dtype=float)
        if beta.shape != self._beta.shape or not np.all(np.isfinite(beta)):
            raise ValueError(f'beta must be {self._beta.size} finite numbers')
        self._beta = beta
        self._beta_version += 1
        self.move_points.reset()  # a move's estimates are of the model they were made with
        if self._pose is not None:
            self._redesign(self._pose)

    # ------------------------------------------------------------------ the loop
    def step(
        self, sample: ControlSample, stale: bool = False, now: float | None = None
    ) -> ControlOutput:
        """One control period. ``stale=True`` (the caller's watchdog) or ``now - sample.t >
        safety.stale_timeout_s`` (when ``now`` is given) or non-finite data -> SAFE_STOP."""
        t = sample.t
        qb = sample.q_base
        dth = sample.pitch_rate
        wl, wr = sample.wheel_left, sample.wheel_right
        rl, rr = sample.wheel_left_rate, sample.wheel_right_rate
        finite = qb == qb and dth == dth and wl == wl and wr == wr and rl == rl and rr == rr
        if finite:
            self._waist = float(sample.joints[0])
        k_step = self._k
        self._k = k_step + 1
        if (
            finite
            and not stale
            and (
                sample.joints_moving
                or self._moving
                or self._pose is None
                or k_step % self._pose_check_every == 0
            )
        ):
            self._track_pose(t, sample.joints, sample.joints_moving)
        # 1. state
        r = self.r
        x = r * (0.5 * (wl + wr) + qb)
        dx = r * (0.5 * (rl + rr) + dth)
        psi = 0.5 * (wr - wl)
        dpsi = 0.5 * (rr - rl)
        theta = qb + self._offset
        tp = self._t_prev
        dt = self.h if tp is None else t - tp
        if not 0.2 * self.h <= dt <= 5.0 * self.h:
            dt = self.h
        self._t_prev = t
        # 2. safety, 3. mode
        mode_before = self.modes.mode
        if mode_before is Mode.STAND_UP or mode_before is Mode.BALANCE or self.stand.tries:
            self._safety(t, dx, qb, mode_before, finite)  # (SIT after a caught stand-up too)
        if (
            mode_before is Mode.BALANCE
            and self._steady
            and finite
            and not stale
            and (now is None or now - t <= self.modes.stale_timeout_s)
        ):
            # the mode machine can do nothing in BALANCE without a request, stale data or a fall
            # check (modes.py): skip building its inputs (the 500 Hz hot path)
            mode, ground_gains, events = mode_before, None, []
        else:
            mode, ground_gains, events = self._mode(
                sample, mode_before, theta, x, dx, psi, finite, stale, now
            )
        # 4./5. the mode's law, 6. clamping
        point = None
        moved = ()
        trim = fx = ft = 0.0
        sat = converged = False
        if mode is Mode.BALANCE:
            il, ir, fx, ft, sat, trim, point, moved, converged = self._balance_law(
                sample, theta, x, dx, dth, psi, dpsi, dt, k_step + 1, events
            )
        elif ground_gains is None:
            il = ir = 0.0
        else:
            th = theta
            if mode is Mode.STAND_UP:  # the stand PD about the stand-up's estimate (stand.py)
                th -= self._stand_watch(t, qb, theta, x, dx, dth, dt)
            il, ir = self._ground_law(ground_gains, t, mode, qb, th, x, dx, dth, psi, dpsi)
        fl = fr = 0.0
        ic, v0, iv = self._coulomb
        if (ic or iv) and (mode is Mode.BALANCE or mode is Mode.STAND_UP):
            # the drive chain's friction opposes the wheels' motion relative to the body
            fl = ic * math.tanh(rl / v0) + iv * rl
            fr = ic * math.tanh(rr / v0) + iv * rr
            il += fl
            ir += fr
        il, ir, clamped = self._clamp(il, ir)
        self.stand.last_current = 0.5 * (il + ir)
        k = self.k_motor
        if (mode is Mode.BALANCE and self._balance_point_active) or (
            mode is Mode.STAND_UP and self.stand.lifted_t is not None and self.balance_point
        ):
            # the torque that reaches the wheels past the friction the compensation expects
            self.balance_point.applied((il + ir - fl - fr) * k, theta, dx, dth)
        out = ControlOutput(
            mode.value,
            il * k,
            ir * k,
            il,
            ir,
            point,
            theta,
            x,
            fx,
            ft,
            events,
            dth,
            dx,
            self.x_ref,
            psi,
            sat or clamped,
            trim,
            converged,
            moved,
        )
        self.last_output = out
        return out

    def _safety(self, t, dx, qb, mode, finite) -> None:
        """Our stops in STAND_UP/BALANCE (and SIT after a caught stand-up): a runaway speed, a
        stand-up that does not settle; the caster catches of STAND_UP (stand.py) and BALANCE (sit
        where the robot is, auto_stand suspended)."""
        max_speed, timeout = self._safety_limits
        catch = self.config.safety.caster_catch_s
        if mode is Mode.STAND_UP and finite and self.stand.caught(t, qb):
            self._on_caster = True  # SIT; once out of tries until the operator's stand_up
            self._sit_requested = self._sit_requested or self.stand.exhausted
            self._stop_reason = self.stand.why()
            if self._stand_asked and not self.stand.exhausted:
                self._stand_once = True  # the operator's stand_up goes on through its tries
            self._requests()
        caster = self._caster
        if catch and mode is Mode.BALANCE and finite:
            if caster.update(t, qb) and not self._on_caster:
                self._on_caster = True
                self._sit_requested = True
                self._stop_reason = (
                    f'caster contact: IMU pitch {caster.pitch:+.4f} rad (low-passed) below '
                    f'{caster.limit:+.4f} for {catch:g} s'
                )
                self._requests()
        why = None
        if mode is Mode.SIT and self.stand.still_rolling(t):
            why = f'still rolling on its caster {self.stand.stop_s:g} s after a caught stand-up'
        elif max_speed and abs(dx) > max_speed and finite:
            why = f'speed {dx:.2f} m/s above max_speed_m_s'
        elif timeout and mode is Mode.STAND_UP and t - self._t_stand > timeout:
            why = f'stand-up not settled within {timeout:g} s'
        if why is not None:
            self._stop_requested = True
            self._stop_reason = why
            self._requests()

    def _mode(self, sample, mode_before, theta, x, dx, psi, finite, stale, now):
        """The mode machine's step and what entering a mode does (references, observer resets).
        Returns (mode, PD gains of a ground mode or None, events)."""
        modes = self.modes
        t = sample.t
        stop = self._stop_requested or not self.enabled
        sit = self._sit_requested and (mode_before is Mode.STAND_UP or mode_before is Mode.BALANCE)
        reset = self._reset_pending
        stand = (
            self.enabled
            and mode_before is Mode.SIT
            and not self._sit_requested
            and (self._auto_stand or self._stand_once)
            and self.stand.ready(
                t, dx, sample.pitch_rate, sample.joints_moving or sample.move_pending
            )
        )
        if stale or not finite:
            last_t = -math.inf
            mt = t if finite else 0.0
        elif now is not None:
            last_t, mt = t, now
        else:
            last_t, mt = None, t
        qb = sample.q_base
        mo = modes.step(
            ModeInputs(
                t=mt,
                imu_pitch=qb if finite else 0.0,
                theta_com=theta if finite else 0.0,
                dtheta=sample.pitch_rate if finite else 0.0,
                waist=float(sample.joints[0]),
                last_sensor_t=last_t,
                stand_request=stand,
                sit_request=sit,
                stop_request=stop,
                reset_request=reset,
                on_caster=self._on_caster,
            )
        )
        if reset and (mode_before is not Mode.SAFE_STOP or mo.mode is not Mode.SAFE_STOP):
            self._reset_pending = False  # consumed; kept while SAFE_STOP refuses it (stale data)
            self._requests()
        if stand and self._stand_once and mo.mode is not Mode.SIT:
            self._stand_once = False
            self._stand_asked = True
        events = []
        for e in mo.events:
            if e.startswith('stand_refused'):
                if self._stand_once:
                    self._stand_once = False  # an operator's request is answered once
                elif self._refused:
                    continue
                self._refused = True
            events.append(e)
        mode = mo.mode
        if mo.entered:
            self._enter(mode, t, theta, x, dx, psi, sample.pitch_rate, events)
        return mode, None if mo.zero_torque else mo.gains, events

    def _enter(self, mode, t, theta, x, dx, psi, dth, events) -> None:
        self._refused = False
        if mode is Mode.BALANCE or mode is Mode.SAFE_STOP:
            self._stand_asked = False
        if mode is Mode.STAND_UP:
            self._t_stand = t
            self.stand.enter()
        if mode is Mode.SIT_DOWN:
            self._sit_from = (t, theta - self._offset)  # the IMU pitch now
        if mode is Mode.SIT and self._on_caster:
            self._on_caster = False
            events.append(f'sit reason: {self._stop_reason}')
            self._stop_reason = None
        if mode is Mode.SAFE_STOP and self._stop_reason:
            events.append(f'stop reason: {self._stop_reason}')
            self._stop_reason = None
        self._on_caster = False
        self._caster.reset()
        # the stand-up's estimate of the CoM-angle error (0 if the observer did not watch it):
        # BALANCE starts at it, where the robot stands (stand.py, "Hand over")
        balance = mode is Mode.BALANCE
        trim = self.stand.balanced() if balance and self._balance_point_active else 0.0
        if mode is Mode.STAND_UP or (balance and (self.config.rezero_x_on_balance or trim)):
            self.x_ref, self.psi_ref = x, psi
        if mode is Mode.BALANCE:
            self._t_balance = t
            self.psi_ref = psi
            self.adrc.reset((theta - trim, x - self.x_ref, dth, dx))
            if self.balance_point is not None:
                self.balance_point.reset(theta, dth, x - self.x_ref, dx, delta=trim)
        else:
            self.detector.reset()
        self.move_points.reset()

    def _balance_law(self, sample, theta, x, dx, dth, psi, dpsi, dt, k, events):
        """ADRC about the balance point, the BalLo spin PD, and the detector's feed. Returns
        (i_left, i_right, f_hat_x, f_hat_theta, saturated, trim, balanced point or None, the
        points read on a move that just ended, converged). Converged, the flag the pose server
        pauses a move on: while the observer is held (the joints move, measured, or stopped less
        than its hold ago) the robot keeps its place (|x - x_ref| and |dx| within
        ``balance_point.place_tol_m`` / ``place_speed_m_s``: the observer's raw estimate then
        carries the joints' reaction torques, and only its averages say something); at rest the
        joints have been still for the hold and one time constant and the estimate has caught up
        (``BalancePointObserver.converged``). The detector takes no point while a move is pending
        or the joints move; meanwhile the observer's estimate of the balance pitch feeds
        ``move_points``, which gives its points when the move ends."""
        t = sample.t
        trim = 0.0
        theta_c = theta
        moved = ()
        bp = self.balance_point
        if bp is None:
            converged = not self._moving or self._keeps_place(x, dx)
        else:
            still = t - self._t_still
            held = self._moving or still < bp.hold_s
            converged = self._keeps_place(x, dx) if held else True
        if self._balance_point_active:
            # regulate about the balance point the observer found (theta_c = 0 there)
            hold = not bp.track_moves and held
            trim = bp.update(theta, dt, hold, x - self.x_ref)
            theta_c = theta - trim
            mp = self.move_points
            if mp.enabled:
                if sample.joints_moving or sample.move_pending:
                    # where the observer puts the balance: theta = raw there
                    mp.add(t, bp.raw - self._offset, sample.joints, sample.joints_moving)
                elif mp.active:
                    moved = mp.end()
            if not held:
                converged = bool(  # a numpy bool would reach std_msgs/Bool as false
                    still >= bp.hold_s + bp.time_constant
                    and t - self._t_balance >= bp.hold_s + bp.time_constant
                    and bp.converged
                )
        c = self.adrc.update(theta_c, x - self.x_ref, dt, dtheta=dth, dx=dx)
        il, ir = c.i_left, c.i_right
        if self._balance_point_active and bp.drive:
            # the drive chain's torque error, cancelled on both wheels alike
            i_drive = -0.5 * bp.drive / self.k_motor
            il += i_drive
            ir += i_drive
        kp, kd, lim = self._spin
        if kp or kd:
            u_spin = -(kp * (psi - self.psi_ref) + kd * dpsi)
            u_spin = -lim if u_spin < -lim else (lim if u_spin > lim else u_spin)
            il += u_spin
            ir -= u_spin
        point = None
        acc = self._gravity_pitch  # every sample's, averaged over the detector's decimation
        acc[0] += sample.gravity_pitch
        acc[1] += 1
        if k % self._detector_every == 0:
            point = self.detector.update(
                t,
                sample.q_base,
                dth,
                dx,
                c.fhat_theta,
                sample.joints,
                sample.joints_moving or sample.move_pending,
                gravity_pitch=acc[0] / acc[1],
            )
            acc[0], acc[1] = 0.0, 0
            if point is not None:
                self.points.append(point)
                events.append(f'balanced_point: q_base={point.q_base:.5f}')
        return il, ir, c.fhat_x, c.fhat_theta, c.saturated, trim, point, moved, converged

    def _stand_watch(self, t, qb, theta, x, dx, dth, dt) -> float:
        """STAND_UP: from lift-off the balance-point observer watches (stand.py); returns the
        CoM angle the stand PD regulates to."""
        stand, bp = self.stand, self.balance_point
        if bp is None or not stand.enabled:
            return 0.0
        if stand.lifts_off(t, qb):
            bp.reset(theta, dth, x - self.x_ref, dx, delta=stand.trim)
        if stand.lifted_t is not None:
            bp.update(theta, dt, False, x - self.x_ref)
            stand.watch(t, bp.raw)
        return stand.reference(qb, theta)

    def _keeps_place(self, x, dx) -> bool:
        """The robot stays near its position reference and slow (the flag during a move)."""
        tol, speed = self._place
        return bool(abs(x - self.x_ref) < tol and abs(dx) < speed)

    def _sit_ref(self, t) -> float:
        """SIT_DOWN's pitch reference: from the pitch at the request down to the sit limit at
        modes.sit_rate_rad_s (a step when 0)."""
        modes = self.config.modes
        if not modes.sit_rate_rad_s:
            return modes.sit_imu_limit_rad
        return max(
            modes.sit_imu_limit_rad,
            self._sit_from[1] - modes.sit_rate_rad_s * (t - self._sit_from[0]),
        )

    def _ground_law(self, g, t, mode, qb, theta, x, dx, dth, psi, dpsi):
        """The PD of SIT, STAND_UP and SIT_DOWN (A per wheel radian, modes.py); SIT_DOWN's theta
        error is the IMU pitch above the sit limit."""
        modes = self.config.modes
        r = self.r
        e_th = qb - self._sit_ref(t) if mode is Mode.SIT_DOWN else theta
        gs = self._ground_scale
        u_th = gs * (g[0] * e_th + g[1] * dth)
        u_x = gs * (g[2] * ((x - self.x_ref) / r) + g[3] * (dx / r))
        if mode is Mode.SIT and self.stand.tries:  # the robot may roll on its caster
            u_th, u_x = self.stand.after_catch(u_th, u_x, qb, dth, dx, self._stand_gains)
        u_spin = -(g[4] * (psi - self.psi_ref) + g[5] * dpsi)
        lim = modes.spin_limit_a
        u_spin = -lim if u_spin < -lim else (lim if u_spin > lim else u_spin)
        return u_th + u_x + u_spin, u_th + u_x - u_spin

    def _clamp(self, il, ir):
        """Each wheel's current to the drive train's limit; returns (i_left, i_right, clamped)."""
        lim = self._current_limit
        sat = False
        if il > lim or il < -lim:
            il = lim if il > 0 else -lim
            sat = True
        if ir > lim or ir < -lim:
            ir = lim if ir > 0 else -lim
            sat = True
        return il, ir, sat
