"""The balancing controller as one object: sit -> stand up -> balance (ADRC on LQR(q)), safe stop,
and the balanced-pose detector. Pure Python, no rclpy; used by the offline closed loop
(``krang_sim.closed_loop``) and by the ROS node.

One ``step(sample)`` per control period:

1. **State.** ``theta`` = CoM angle from vertical of the WHOLE robot (wheels included) computed from
   the IMU pitch, the joint encoders and the ESTIMATED beta, as the hardware did
   (``theta = q_base + com_offset_full(joints, beta)``, krang_model.wip). ``x = r (mean(wheel
   encoders) + q_base)`` in metres (FACTS §2: ground-referenced wheel angle), ``dx`` likewise from
   the wheel rates and the pitch rate, ``dtheta`` = IMU pitch rate, ``psi = (right - left) / 2``
   wheel radians (spin).
2. **Modes** (``modes.ModeMachine``): SIT (ground PD), STAND_UP (the hardware's stand PD, in A per
   wheel radian), BALANCE (ADRC), SIT_DOWN, SAFE_STOP (zero torque; on a stop request, a disable,
   stale or non-finite data). While enabled and sitting, a stand request is issued every step
   (``auto_stand``), refused by the mode machine when theta is outside the stand window.
3. **LQR(q)** through ``lqr.GainCache`` on ``wip.linearize(wip.reduce_pose(pose, beta))``, redone
   only when the pose or beta changes: a settled pose is compared with its reference every
   ``pose_check_period_s``; while the joints move, the CoM offset is refreshed every
   ``pose_update_period_s`` and the LQR every ``gain_update_period_s`` (both again when motion stops).
4. **ADRC** (``adrc.AdrcController``, the paper's law with the authors' ESO input). The hot path is
   a scalar re-implementation of ``AdrcController.update`` on the same discretisation matrices
   (``fast_path``; equal to it to rounding, see test_controller.py), because numpy's per-call cost
   on 3-vectors would dominate a 500 Hz loop. The spin PD of the hardware's BalLo mode is added
   per wheel.
5. **Detector** (``detector.BalancedPoseDetector``), fed in BALANCE at ``detector_rate_hz`` with
   the measured q_base, the pitch rate, the ground speed (m/s) and the theta-ESO's f_hat (rad/s^2;
   its noise does not depend on the pose, unlike the compensation torque's). It returns one point
   per settled pose:
   the window means of all joints and of the measured q_base.

Notes. With the authors' ESO input alone the ADRC comes to rest where plain LQR does,
x - x_ref = -F_theta0 delta / F_x0 (delta = theta error of the beta), with the TRUE CoM over the axle
(adrc.py). The balance-point observer (balance_point.py, ``balance_point_observer``) estimates delta
and the ADRC regulates theta - delta_hat, so the robot rests at x_ref. Either rest is what the detector
needs: its q_base is the true balance pitch whatever the beta. ``rezero_x_on_balance`` (default off)
reproduces the 2018 code's reset of the x reference at every mode change; off, the ADRC keeps the
stand-up's reference and the handover does not move the robot a second time.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from krang_model.com import base_regressor
from krang_model.drivetrain import drivetrain
from krang_model.wip import linearize, reduce_pose

from .adrc import AdrcController
from .balance_point import BalancePointObserver
from .detector import BalancedPoint, BalancedPoseDetector
from .eso import AUTHORS_CONTINUOUS_GAINS
from .lqr import AUTHORS_Q_DIAG, AUTHORS_R, GainCache, LqrDesigner
from .modes import (GROUND_LO_GAINS, SIT_GAINS, STAND_GAINS, Mode, ModeInputs, ModeMachine, ModeOutput)

NODE_NAME = 'adrc_controller'
DEG = math.pi / 180.0


def single_thread_blas() -> int:
    """Limit the OpenBLAS libraries loaded in this process (numpy's and scipy's) to one thread.

    Why: the LQR(q) redesign (python-control -> scipy -> LAPACK) on 4x4 matrices gains nothing from
    threads, but on a loaded machine OpenBLAS's thread pool turned a 1 ms design into 20-65 ms
    (measured on the shared 2-core dev box), stalling the 500 Hz loop. Same effect as
    OPENBLAS_NUM_THREADS=1 set before numpy is imported. Linux only; returns the number of libraries
    changed (0 when none is found)."""
    import ctypes
    try:
        with open('/proc/self/maps') as f:
            libs = sorted({line.split()[-1] for line in f if 'openblas' in line.lower() and '/' in line})
    except OSError:
        return 0
    changed = 0
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in ('scipy_openblas_set_num_threads64_', 'scipy_openblas_set_num_threads',
                     'openblas_set_num_threads64_', 'openblas_set_num_threads'):
            fn = getattr(lib, name, None)
            if fn is not None:
                fn(1)
                changed += 1
                break
    return changed


# ----------------------------------------------------------------------------- configuration


@dataclass
class ControllerConfig:
    """Every parameter of the controller; defaults = config/controller.yaml (documented there).
    Where ROS parameters cannot be null, 0.0 means "off" / "from robot.yaml" (see the YAML)."""

    rate_hz: float = 500.0
    # LQR(q): Q over [x, xdot, theta, thetadot] with x in wheel radians; R on the total torque
    lqr_q_diag: tuple = AUTHORS_Q_DIAG
    lqr_r: float = AUTHORS_R
    gain_update_period_s: float = 0.1
    pose_update_period_s: float = 0.02
    pose_tol_rad: float = 2e-3
    pose_check_period_s: float = 0.1
    # ADRC / ESO
    use_disturbance_rejection: bool = True
    eso_method: str = 'current'
    eso_omega_o: float = 20.0
    eso_continuous_gains: tuple = AUTHORS_CONTINUOUS_GAINS
    eso_input: str = 'nominal'
    f_limit_x: float = 0.0
    f_limit_theta: float = 0.0
    use_measured_rates: bool = True
    # balance-point observer (balance_point.py): reject the wrong CoM through the lean, so the robot rests at x_ref
    balance_point_observer: bool = True
    balance_point_time_constant_s: float = 1.0
    balance_point_limit_rad: float = 0.3
    balance_point_hold_s: float = 0.5   # delta_hat held this long after the joints stop (the ESO re-converges)
    rezero_x_on_balance: bool = False
    fast_path: bool = True
    single_thread_blas: bool = True    # see single_thread_blas()
    # drive
    current_limit_a: float = 49.0
    torque_constant_nm_per_a: float = 0.0
    gear_ratio: float = 0.0
    spin_gains: tuple = (0.0, -10.0)
    spin_limit_a: float = 30.0
    # modes
    auto_stand: bool = True
    start_enabled: bool = False
    stand_error_min_rad: float = -0.20944       # -12 deg
    stand_error_max_rad: float = 0.0
    balance_imu_min_rad: float = -1.76278       # -101 deg
    balance_rate_max: float = 0.03
    stand_settle_s: float = 3.33
    sit_waist_min_rad: float = 2.61799          # 150 deg
    sit_imu_limit_rad: float = -1.75406         # -100.5 deg
    stale_timeout_s: float = 0.1
    fall_angle_rad: float = 0.0
    stand_timeout_s: float = 20.0      # STAND_UP longer than this -> stop (0 = off)
    max_speed_m_s: float = 3.0         # |dx| above this in STAND_UP/BALANCE -> stop (0 = off)
    ground_gains: tuple = GROUND_LO_GAINS
    stand_gains: tuple = STAND_GAINS
    sit_gains: tuple = SIT_GAINS
    # detector
    detector_rate_hz: float = 50.0
    detector_window_s: float = 2.0
    detector_pitch_rate_max: float = 0.03
    detector_wheel_speed_max: float = 0.008
    detector_fhat_band: float = 0.6
    detector_joint_tol_rad: float = 2e-3
    detector_rearm_tol_rad: float = 0.02
    detector_q_base_std_max: float = 0.0
    detector_min_samples: int = 10

    @classmethod
    def from_dict(cls, values: dict, *, strict: bool = True) -> 'ControllerConfig':
        """From flat parameters (unknown keys raise unless strict=False); lists become tuples."""
        names = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(names))
        if unknown and strict:
            raise ValueError(f'unknown controller parameters: {unknown}')
        kw = {}
        for k, v in values.items():
            if k not in names:
                continue
            kw[k] = tuple(float(e) for e in v) if isinstance(v, (list, tuple)) else v
        cfg = cls(**kw)
        cfg.validate()
        return cfg

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    def replace(self, **changes) -> 'ControllerConfig':
        d = asdict(self)
        d.update(changes)
        return ControllerConfig.from_dict(d)

    def validate(self) -> None:
        if self.rate_hz <= 0:
            raise ValueError('rate_hz must be positive')
        if len(self.lqr_q_diag) != 4 or self.lqr_r <= 0:
            raise ValueError('lqr_q_diag needs 4 entries and lqr_r > 0')
        for name in ('ground_gains', 'stand_gains', 'sit_gains'):
            if len(getattr(self, name)) != 6:
                raise ValueError(f'{name} needs 6 gains (th, dth, x, dx, psi, dpsi)')
        if len(self.spin_gains) != 2:
            raise ValueError('spin_gains needs (psi, dpsi)')
        if self.eso_input not in ('nominal', 'applied') or self.eso_method not in ('current', 'zoh'):
            raise ValueError('eso_input must be nominal|applied and eso_method current|zoh')
        if self.detector_rate_hz <= 0 or self.detector_rate_hz > self.rate_hz:
            raise ValueError('detector_rate_hz must be in (0, rate_hz]')
        if self.current_limit_a <= 0 or self.stale_timeout_s <= 0:
            raise ValueError('current_limit_a and stale_timeout_s must be positive')
        if self.balance_point_time_constant_s <= 0 or self.balance_point_limit_rad <= 0 or self.balance_point_hold_s < 0:
            raise ValueError('balance_point_time_constant_s and balance_point_limit_rad must be positive, '
                             'balance_point_hold_s not negative')


def default_config_path() -> Path:
    from krang_model.config import config_path
    return config_path('controller.yaml')


def load_controller_config(path=None, overrides: dict | None = None) -> ControllerConfig:
    """ControllerConfig from a node-parameter YAML (``adrc_controller: ros__parameters: {...}``, or a
    plain flat mapping); default config/controller.yaml. ``overrides`` are applied on top."""
    import yaml
    path = Path(path) if path else default_config_path()
    with open(path) as f:
        doc = yaml.safe_load(f) or {}
    if NODE_NAME in doc:
        doc = doc[NODE_NAME]
    if 'ros__parameters' in doc:
        doc = doc['ros__parameters']
    values = dict(doc)
    values.update(overrides or {})
    return ControllerConfig.from_dict(values)


# ----------------------------------------------------------------------------- samples / outputs


@dataclass(slots=True)
class ControlSample:
    """One synchronised sensor sample. Angles rad, rates rad/s, t in s (sensor clock)."""
    t: float
    q_base: float               # IMU pitch (FACTS §2 convention)
    pitch_rate: float
    wheel_left: float           # wheel encoder angles relative to the body (rad, wheel side)
    wheel_right: float
    wheel_left_rate: float
    wheel_right_rate: float
    joints: np.ndarray          # body joints, pose order
    joints_moving: bool = False


@dataclass(slots=True)
class ControlOutput:
    mode: str
    torque_left: float          # N m at the wheel
    torque_right: float
    current_left: float         # A at the motor (positive drives x forward)
    current_right: float
    balanced_point: BalancedPoint | None
    theta: float                # CoM angle from vertical with the estimated beta (rad)
    x: float                    # ground-referenced wheel position r (mean encoders + q_base), m
    f_hat_x: float
    f_hat_theta: float
    events: list = field(default_factory=list)
    dtheta: float = 0.0         # rad/s (IMU rate)
    dx: float = 0.0             # m/s
    x_ref: float = 0.0          # m, the position reference of STAND_UP/BALANCE
    psi: float = 0.0            # wheel radians
    saturated: bool = False
    balance_trim: float = 0.0   # rad, the balance-point observer's delta_hat (0 when it is off)


def sample_from_sensors(sensors, joints_moving: bool = False) -> ControlSample:
    """ControlSample from a ``krang_sim.physics.Sensors`` reading."""
    return ControlSample(sensors.t, sensors.q_base, sensors.pitch_rate, sensors.wheel_left,
                         sensors.wheel_right, sensors.wheel_left_rate, sensors.wheel_right_rate,
                         sensors.joints, joints_moving)


# ----------------------------------------------------------------------------- scalar ADRC


class _ScalarAdrc:
    """``AdrcController.update`` in scalar floats on the controller's own discretisations.

    Same equations and order of operations as adrc.py/eso.py (per rounded dt the ESO's
    ``discretisation(dt)`` matrices are converted to floats once). The AdrcController keeps the
    design (gains, b's, ESO settings); this object keeps the running state.
    """

    def __init__(self, ctl: AdrcController):
        self.ctl = ctl
        self._disc = {}
        self._last_dt = None
        self._last = None
        self.zx = [0.0, 0.0, 0.0]
        self.zt = [0.0, 0.0, 0.0]
        self.yprev_x = 0.0
        self.yprev_t = 0.0
        self.u_prev_x = 0.0
        self.u_prev_t = 0.0
        self.sync()

    def sync(self):
        """Re-read gains and b's (call after AdrcController.set_gains)."""
        c = self.ctl
        self.fx0, self.fx1 = float(c.f_x[0]), float(c.f_x[1])
        self.ft0, self.ft1 = float(c.f_theta[0]), float(c.f_theta[1])
        self.b_x, self.b_t = c.b_x, c.b_theta
        self.flx = c.eso_x.f_limit
        self.flt = c.eso_theta.f_limit
        self._disc.clear()
        self._last_dt = None

    def _discretisation(self, dt):
        key = round(dt, 6)
        d = self._disc.get(key)
        if d is None:
            out = []
            for eso in (self.ctl.eso_x, self.ctl.eso_theta):
                m = eso.discretisation(dt)
                out.append((tuple(float(v) for v in np.asarray(m.phi).ravel()),
                            tuple(float(v) for v in m.gam_u), tuple(float(v) for v in m.gam_y)))
            d = (out[0], out[1], self.ctl.eso_x.method == 'zoh')
            if len(self._disc) > 64:
                self._disc.clear()
            self._disc[key] = d
        return d

    def reset(self, theta, x, dtheta, dx):
        self.zt = [float(theta), float(dtheta), 0.0]
        self.zx = [float(x), float(dx), 0.0]
        self.yprev_t, self.yprev_x = float(theta), float(x)
        self.u_prev_x = self.u_prev_t = 0.0

    @staticmethod
    def _eso(z, disc, u, y, flim):
        """z <- phi z + gam_u u + gam_y y (eso.ExtendedStateObserver.update), in place."""
        p, gu, gy = disc
        z0, z1, z2 = z
        n0 = p[0] * z0 + p[1] * z1 + p[2] * z2 + gu[0] * u + gy[0] * y
        n1 = p[3] * z0 + p[4] * z1 + p[5] * z2 + gu[1] * u + gy[1] * y
        n2 = p[6] * z0 + p[7] * z1 + p[8] * z2 + gu[2] * u + gy[2] * y
        if flim is not None:
            n2 = -flim if n2 < -flim else (flim if n2 > flim else n2)
        z[0], z[1], z[2] = n0, n1, n2

    def update(self, theta, x, dt, dtheta, dx):
        """Returns (tau_total_cmd_l, tau_r, i_l, i_r, u_x, u_th, fhat_x, fhat_t, saturated)."""
        if dt != self._last_dt:
            self._last = self._discretisation(dt)
            self._last_dt = dt
        dxd, dtd, zoh = self._last
        zx, zt = self.zx, self.zt
        if zoh:      # the 'zoh' ESO is a predictor: it uses the previous measurement
            self._eso(zx, dxd, self.u_prev_x, self.yprev_x, self.flx)
            self._eso(zt, dtd, self.u_prev_t, self.yprev_t, self.flt)
            self.yprev_x, self.yprev_t = x, theta
        else:
            self._eso(zx, dxd, self.u_prev_x, x, self.flx)
            self._eso(zt, dtd, self.u_prev_t, theta, self.flt)
        vx = zx[1] if dx is None else dx
        vt = zt[1] if dtheta is None else dtheta
        u_x = -(self.fx0 * x + self.fx1 * vx)
        u_th = -(self.ft0 * theta + self.ft1 * vt)
        c = self.ctl
        if c.use_disturbance_rejection:
            tx = u_x - zx[2] / self.b_x
            tt = u_th - zt[2] / self.b_t
        else:
            tx, tt = u_x, u_th
        tau_cmd = tx + tt
        # AdrcController._to_wheels
        k = c.gear * c.kt
        lim = c.current_limit
        sat = False
        res = []
        for tau in (c.left_share * tau_cmd, (1.0 - c.left_share) * tau_cmd):
            if c.torque_limit is not None and abs(tau) > c.torque_limit:
                tau = math.copysign(c.torque_limit, tau)
                sat = True
            i = tau / k
            if abs(i) > lim:
                i = math.copysign(lim, i)
                sat = True
            res.append(i)
        i_l, i_r = res
        if c.eso_input == 'nominal':
            self.u_prev_x, self.u_prev_t = u_x, u_th
        else:
            tau_total = i_l * k + i_r * k
            scale = tau_total / tau_cmd if tau_cmd != 0 else 1.0
            self.u_prev_x, self.u_prev_t = tx * scale, tt * scale
        return i_l * k, i_r * k, i_l, i_r, u_x, u_th, zx[2], zt[2], sat

    def export_state(self):
        """Copy the running state into the AdrcController's observers (for inspection)."""
        c = self.ctl
        c.eso_x.z = np.array(self.zx)
        c.eso_theta.z = np.array(self.zt)
        c._u_prev_x, c._u_prev_theta = self.u_prev_x, self.u_prev_t


# ----------------------------------------------------------------------------- the controller


class BalanceController:
    """See the module docstring. ``robot`` from ``krang_model.robot.load_krang()``."""

    def __init__(self, robot, beta, config: ControllerConfig | None = None):
        self.robot = robot
        self.config = cfg = config if config is not None else load_controller_config()
        cfg.validate()
        if cfg.single_thread_blas:
            single_thread_blas()
        self.h = 1.0 / cfg.rate_hz
        drive = drivetrain(robot)
        self.drive = drive
        self.r = drive.wheel_radius
        self.kt = cfg.torque_constant_nm_per_a or drive.torque_constant
        self.gear = cfg.gear_ratio or drive.gear_ratio
        self.k_motor = self.kt * self.gear          # wheel N m per motor A
        self.designer = LqrDesigner(cfg.lqr_q_diag, cfg.lqr_r, position_unit='m', wheel_radius_m=self.r)
        self.gains = GainCache(self._linearize, self.designer)
        self.modes = ModeMachine(
            stand_error_min_rad=cfg.stand_error_min_rad, stand_error_max_rad=cfg.stand_error_max_rad,
            balance_imu_min_rad=cfg.balance_imu_min_rad, balance_rate_max=cfg.balance_rate_max,
            stand_settle_s=cfg.stand_settle_s, sit_waist_min_rad=cfg.sit_waist_min_rad,
            sit_imu_limit_rad=cfg.sit_imu_limit_rad, stale_timeout_s=cfg.stale_timeout_s,
            fall_angle_rad=cfg.fall_angle_rad or None, ground_gains=cfg.ground_gains,
            stand_gains=cfg.stand_gains, sit_gains=cfg.sit_gains,
            initial_mode=Mode.SIT if cfg.start_enabled else Mode.SAFE_STOP)
        self.detector = BalancedPoseDetector(
            window_s=cfg.detector_window_s, pitch_rate_max=cfg.detector_pitch_rate_max,
            wheel_speed_max=cfg.detector_wheel_speed_max, fhat_band=cfg.detector_fhat_band,
            joint_tol_rad=cfg.detector_joint_tol_rad, rearm_tol_rad=cfg.detector_rearm_tol_rad,
            q_base_std_max=cfg.detector_q_base_std_max or None, max_gap_s=max(0.2, 3.0 / cfg.detector_rate_hz),
            min_samples=cfg.detector_min_samples)
        self._detector_every = max(1, int(round(cfg.rate_hz / cfg.detector_rate_hz)))
        self._pose_check_every = max(1, int(round(cfg.pose_check_period_s * cfg.rate_hz)))
        self.enabled = bool(cfg.start_enabled)
        self._stop_requested = False
        self._sit_requested = False
        self._reset_pending = False
        self._beta = np.array(beta, dtype=float)
        self._beta_version = 0
        self._body_memo = None
        self._pose = None                # reference pose of the current design
        self._offset = 0.0               # theta = q_base + offset (whole robot, estimated beta)
        self._design = None
        self.adrc = None
        self._fast = None
        self.balance_point = None        # BalancePointObserver when config.balance_point_observer
        self._moving = False
        self._t_still = -math.inf        # when the joints last stopped
        self._t_offset = -math.inf
        self._t_gain = -math.inf
        self._t_prev = None
        self._k = 0
        self.x_ref = 0.0
        self.psi_ref = 0.0
        self._refused = False
        self._t_stand = 0.0
        self._stop_reason = None
        self._steady_balance = ModeOutput(Mode.BALANCE, 'adrc', None, False, False, ())
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

    def set_beta(self, beta) -> None:
        """New estimate: the CoM reference (theta offset) and LQR(q) follow at once."""
        beta = np.array(beta, dtype=float)
        if beta.shape != self._beta.shape or not np.all(np.isfinite(beta)):
            raise ValueError(f'beta must be {self._beta.size} finite numbers')
        self._beta = beta
        self._beta_version += 1
        if self._pose is not None:
            self._redesign(self._pose)

    def set_enabled(self, enabled: bool) -> None:
        """False -> SAFE_STOP (zero torque) from the next step; True -> leave SAFE_STOP to SIT (needs
        fresh data) and, with auto_stand, stand up. Also clears a request_stop()."""
        self.enabled = bool(enabled)
        if self.enabled:
            self._stop_requested = False
            self._sit_requested = False
            self._reset_pending = True
            self._refused = False

    def request_sit(self) -> None:
        """Sit down on the caster (STAND_UP/BALANCE -> SIT_DOWN -> SIT), if the waist allows it
        (modes.py). auto_stand is suspended until set_enabled(True) is called again."""
        self._sit_requested = True

    def request_stop(self) -> None:
        """Latched stop: SAFE_STOP (zero torque) until set_enabled(True)."""
        self._stop_requested = True

    def expected_rest_offset(self) -> float:
        """x - x_ref (m) where ADRC/LQR come to rest for a CoM-angle error of 1 rad: -F_th0/F_x0."""
        d = self._design
        return -d['F_theta'][0] / d['F_x'][0]

    # ------------------------------------------------------------------ design
    def _body(self, pose, beta):
        memo = self._body_memo
        if memo is not None and memo[0] is pose and memo[1] == self._beta_version:
            return memo[2]
        body = reduce_pose(self.robot, pose, beta)
        self._body_memo = (pose, self._beta_version, body)
        return body

    def _linearize(self, pose, beta):
        return linearize(self._body(pose, beta), self.drive)

    def _offset_for(self, joints) -> float:
        m = base_regressor(self.robot, np.asarray(joints, float)[None])[0] @ self._beta
        return math.atan2(-m[2], m[1])

    def _redesign(self, pose) -> None:
        """Full update for a (new) reference pose: offset, LQR(q), ADRC gains."""
        pose = np.array(pose, dtype=float)
        same_pose = self._pose is not None and np.array_equal(pose, self._pose)
        self._pose = pose
        body = self._body(pose, self._beta)
        self._shift_offset(body.com_offset_full, same_pose)
        d = self.gains.design(pose, self._beta)
        self._design = d
        self.redesigns += 1
        cfg = self.config
        if self.adrc is None:
            self.adrc = AdrcController.from_design(
                d, sample_period_s=self.h, eso_omega_o=cfg.eso_omega_o or None,
                eso_continuous_gains=cfg.eso_continuous_gains, eso_method=cfg.eso_method,
                f_limit_x=cfg.f_limit_x or None, f_limit_theta=cfg.f_limit_theta or None,
                torque_constant_nm_per_a=self.kt, gear_ratio=self.gear,
                current_limit_a=cfg.current_limit_a,
                use_disturbance_rejection=cfg.use_disturbance_rejection, eso_input=cfg.eso_input)
            self._fast = _ScalarAdrc(self.adrc)
            if cfg.balance_point_observer:
                self.balance_point = BalancePointObserver(self.h, cfg.eso_omega_o or 20.0,
                                                          cfg.balance_point_time_constant_s,
                                                          cfg.balance_point_limit_rad)
        else:
            self.adrc.set_gains(d['F_x'], d['F_theta'], d['b_x'], d['b_theta'])
            self._fast.sync()
        if self.balance_point is not None:
            self.balance_point.set_model(d['A'], d['B'])

    def _shift_offset(self, offset: float, same_pose: bool = False) -> None:
        """New theta offset. The theta-ESO's estimate moves with it (bumpless): a model change is a
        step in the measured theta that no motion caused, and must not read as an acceleration. With the
        balance-point observer the ADRC sees theta - delta_hat: it moves by what delta_hat does not take."""
        delta = offset - self._offset
        self._offset = offset
        if not delta:
            return
        step = delta
        if self.balance_point is not None:
            before = self.balance_point.delta
            self.balance_point.shift(delta, same_pose)
            if self.config.use_disturbance_rejection:
                step -= self.balance_point.delta - before
        if self._fast is not None:
            self._fast.zt[0] += step
            self._fast.yprev_t += step
            self.adrc.eso_theta.z[0] += step
            self.adrc.eso_theta._y_prev += step

    def set_disturbance_rejection(self, enabled: bool) -> None:
        """ADRC (True) or plain LQR (False) in BALANCE."""
        self.config.use_disturbance_rejection = bool(enabled)
        if self.adrc is not None:
            self.adrc.set_disturbance_rejection(enabled)

    def _track_pose(self, t, joints, moving) -> None:
        if self._pose is None:
            self._redesign(joints)
            return
        if moving:
            if not self._moving:
                self._moving = True
                self._t_offset = self._t_gain = -math.inf
            if t - self._t_gain >= self.config.gain_update_period_s:
                self._t_gain = self._t_offset = t
                self._redesign(joints)
            elif t - self._t_offset >= self.config.pose_update_period_s:
                self._t_offset = t
                self._shift_offset(self._offset_for(joints))
            return
        if self._moving:
            self._moving = False
            self._t_still = t
            self._redesign(joints)
            return
        # settled: called every pose_check_period_s by step()
        if float(np.max(np.abs(joints - self._pose))) > self.config.pose_tol_rad:
            self._redesign(joints)

    # ------------------------------------------------------------------ the loop
    def step(self, sample: ControlSample, stale: bool = False, now: float | None = None) -> ControlOutput:
        """One control period. ``stale=True`` (the caller's watchdog) or ``now - sample.t >
        stale_timeout_s`` (when ``now`` is given) or non-finite data -> SAFE_STOP."""
        cfg = self.config
        t = sample.t
        qb = sample.q_base
        dth = sample.pitch_rate
        wl, wr = sample.wheel_left, sample.wheel_right
        finite = (qb == qb and dth == dth and wl == wl and wr == wr
                  and sample.wheel_left_rate == sample.wheel_left_rate
                  and sample.wheel_right_rate == sample.wheel_right_rate)
        joints = sample.joints
        k_step = self._k
        self._k = k_step + 1
        if finite and (sample.joints_moving or self._moving or self._pose is None
                       or k_step % self._pose_check_every == 0):
            self._track_pose(t, joints, sample.joints_moving)
        r = self.r
        x = r * (0.5 * (wl + wr) + qb)
        dx = r * (0.5 * (sample.wheel_left_rate + sample.wheel_right_rate) + dth)
        psi = 0.5 * (wr - wl)
        dpsi = 0.5 * (sample.wheel_right_rate - sample.wheel_left_rate)
        theta = qb + self._offset
        tp = self._t_prev
        dt = self.h if tp is None else t - tp
        if not 0.2 * self.h <= dt <= 5.0 * self.h:
            dt = self.h
        self._t_prev = t

        modes = self.modes
        mode_before = modes.mode
        if mode_before is Mode.STAND_UP or mode_before is Mode.BALANCE:
            why = None
            if cfg.max_speed_m_s and abs(dx) > cfg.max_speed_m_s and finite:
                why = f'speed {dx:.2f} m/s above max_speed_m_s'
            elif (cfg.stand_timeout_s and mode_before is Mode.STAND_UP
                  and t - self._t_stand > cfg.stand_timeout_s):
                why = f'stand-up not settled within {cfg.stand_timeout_s:g} s'
            if why is not None:
                self._stop_requested = True
                self._stop_reason = why
        stop = self._stop_requested or not self.enabled
        stand = self.enabled and cfg.auto_stand and mode_before is Mode.SIT and not self._sit_requested
        sit = self._sit_requested and (mode_before is Mode.STAND_UP or mode_before is Mode.BALANCE)
        reset = self._reset_pending
        fresh = finite and not stale and (now is None or now - t <= modes.stale_timeout_s)
        if (mode_before is Mode.BALANCE and fresh and not stop and not sit and not reset
                and modes.fall_angle is None):
            # the mode machine can do nothing in BALANCE without a request, stale data or a fall
            # check (modes.py): skip building its inputs (the 500 Hz hot path)
            mo = self._steady_balance
        else:
            if stale or not finite:
                last_t = -math.inf
                mt = t if finite else 0.0
            elif now is not None:
                last_t, mt = t, now
            else:
                last_t, mt = None, t
            mo = modes.step(ModeInputs(t=mt, imu_pitch=qb if finite else 0.0, theta_com=theta if finite else 0.0,
                                       dtheta=dth if finite else 0.0, waist=float(joints[0]),
                                       last_sensor_t=last_t, stand_request=stand, sit_request=sit,
                                       stop_request=stop, reset_request=reset))
        if reset and (mode_before is not Mode.SAFE_STOP or mo.mode is not Mode.SAFE_STOP):
            self._reset_pending = False      # consumed; kept while SAFE_STOP refuses it (stale data)
        events = mo.events if mo.events else []
        if events:
            kept = []
            for e in events:
                if e.startswith('stand_refused'):
                    if self._refused:
                        continue
                    self._refused = True
                kept.append(e)
            events = kept
        mode = mo.mode
        if mo.entered:
            self._refused = False
            if mode is Mode.STAND_UP:
                self._t_stand = t
            if mode is Mode.SAFE_STOP and self._stop_reason:
                events.append(f'stop reason: {self._stop_reason}')
                self._stop_reason = None
            if mode is Mode.STAND_UP or (mode is Mode.BALANCE and cfg.rezero_x_on_balance):
                self.x_ref, self.psi_ref = x, psi
            if mode is Mode.BALANCE:
                self.psi_ref = psi
                self._fast.reset(theta, x - self.x_ref, dth, dx)
                self.adrc.reset((theta, x - self.x_ref, dth, dx))
                if self.balance_point is not None:
                    self.balance_point.reset(theta, dth)
            if mode is not Mode.BALANCE:
                self.detector.reset()

        fx = ft = trim = 0.0
        sat = False
        point = None
        balance_point = self.balance_point if mode is Mode.BALANCE and cfg.use_disturbance_rejection else None
        if mode is Mode.BALANCE:
            xr = x - self.x_ref
            # regulate about the balance point the observer found (theta_c = 0 there), not the model's
            theta_c = theta
            if balance_point is not None:
                hold = self._moving or t - self._t_still < cfg.balance_point_hold_s
                trim = balance_point.update(theta, dt, hold)
                theta_c = theta - trim
            if cfg.fast_path:
                if cfg.use_measured_rates:
                    tl, tr, il, ir, _, _, fx, ft, sat = self._fast.update(theta_c, xr, dt, dth, dx)
                else:
                    tl, tr, il, ir, _, _, fx, ft, sat = self._fast.update(theta_c, xr, dt, None, None)
            else:
                rates = cfg.use_measured_rates
                c = self.adrc.update(theta_c, xr, dt, dtheta=dth if rates else None, dx=dx if rates else None)
                il, ir, fx, ft, sat = c.i_left, c.i_right, c.fhat_x, c.fhat_theta, c.saturated
            kp, kd = cfg.spin_gains
            if kp or kd:
                u_spin = -(kp * (psi - self.psi_ref) + kd * dpsi)
                lim = cfg.spin_limit_a
                u_spin = -lim if u_spin < -lim else (lim if u_spin > lim else u_spin)
                il += u_spin
                ir -= u_spin
            if self._k % self._detector_every == 0:
                point = self.detector.update(t, qb, dth, dx, ft, joints, sample.joints_moving)
                if point is not None:
                    self.points.append(point)
                    events.append(f'balanced_point: q_base={point.q_base:.5f}')
        elif mo.zero_torque or mo.gains is None:
            il = ir = 0.0
        else:
            g = mo.gains
            e_th = qb - cfg.sit_imu_limit_rad if mode is Mode.SIT_DOWN else theta
            e_x = (x - self.x_ref) / r
            e_dx = dx / r
            u_th = g[0] * e_th + g[1] * dth
            u_x = g[2] * e_x + g[3] * e_dx
            u_spin = -(g[4] * (psi - self.psi_ref) + g[5] * dpsi)
            lim = cfg.spin_limit_a
            u_spin = -lim if u_spin < -lim else (lim if u_spin > lim else u_spin)
            il = u_th + u_x + u_spin
            ir = u_th + u_x - u_spin
        lim = cfg.current_limit_a
        if il > lim or il < -lim:
            il = lim if il > 0 else -lim
            sat = True
        if ir > lim or ir < -lim:
            ir = lim if ir > 0 else -lim
            sat = True
        k = self.k_motor
        if balance_point is not None:
            balance_point.applied((il + ir) * k, theta, dx, dth)
        out = ControlOutput(mode.value, il * k, ir * k, il, ir, point, theta, x, fx, ft, events,
                            dth, dx, self.x_ref, psi, sat, trim)
        self.last_output = out
        return out
