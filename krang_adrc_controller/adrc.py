"""The paper's ADRC balancing law (§II-D) for the locked-joint WIP, with a plain-LQR switch.

    tau_w = (u_x - f_x_hat / b_x) + (u_theta - f_theta_hat / b_theta)
    u_x = -F_x . [x, xdot],   u_theta = -F_theta . [theta, thetadot]

tau_w is the total wheel torque (both wheels), split ``left_share`` / (1 - left_share) and
converted to motor current through gear ratio and torque constant, then limited.

What each ESO is fed (``eso_input``) matters for this under-actuated plant (one torque, two
channels):

* ``'nominal'`` (default, the authors' code: munzir/18h adrc.cpp and 18d Controller.cpp feed
  u_x and u_theta *before* compensation). At rest each ESO settles at f_hat = -b u_nominal, the
  total torque becomes 2 (u_x + u_theta) = 0 and the equilibrium is the LQR one. The robot still
  comes to rest with its true CoM over the axle; the observer changes the transient.
* ``'applied'`` (textbook ADRC: the ESO sees the input actually applied in its channel). At rest
  each ESO would force its own LQR term to zero, i.e. x = 0 *and* theta_measured = 0. With a
  wrong CoM (theta_measured = theta_true + delta, delta != 0) that point does not exist, and the
  two disturbance estimates wind up in opposite directions without bound while their sum stays
  ~0. It is kept only to show that (test_adrc.py); do not run it on the robot.

Velocities: the law uses measured rates when given (IMU rate, wheel speed), else the ESO
estimates. Gains, b's, limits and motor constants are arguments; defaults cite FACTS.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from .eso import AUTHORS_CONTINUOUS_GAINS, ExtendedStateObserver

#: Motor torque constant, 12 oz-in/A (FACTS §5; the authors' code uses 12 * 0.00706155).
DEFAULT_TORQUE_CONSTANT_NM_PER_A = 12 * 0.00706155
#: GBPH-0902-NS-015 gearbox (FACTS §5).
DEFAULT_GEAR_RATIO = 15.0
#: Current clamp of the paper-era controller (FACTS §5: 49 A in 33-beta-testing, 50 A daemon).
DEFAULT_CURRENT_LIMIT_A = 49.0
#: Mean hardware loop period in the paper's runs (FACTS §7: 0.0333 s).
DEFAULT_SAMPLE_PERIOD_S = 0.0333


@dataclass
class WheelCommand:
    """One control step's output. Torques at the wheels [N m], currents at the motors [A]."""
    tau_left: float
    tau_right: float
    i_left: float
    i_right: float
    tau_total: float
    u_x: float
    u_theta: float
    fhat_x: float
    fhat_theta: float
    saturated: bool


class AdrcController:
    """ADRC (or plain LQR) balancing controller for one locked pose.

    Parameters
    ----------
    f_x, f_theta : LQR gains over [x, xdot] and [theta, thetadot] (``lqr.split_gains``).
    b_x, b_theta : B rows of xddot and thetaddot (``lqr.channel_input_gains``).
    sample_period_s : nominal loop period (default 0.0333 s, FACTS §7).
    eso_omega_o : ESO bandwidth [rad/s]; when None, the authors' continuous gains
        ``eso_continuous_gains`` (default FACTS §7) discretised by ``eso_method``.
    eso_method : 'current' (matched poles / bandwidth) or 'zoh' (see eso.py).
    f_limit_x, f_limit_theta : optional saturation of the disturbance estimates.
    torque_constant_nm_per_a, gear_ratio : motor constant and gearbox (FACTS §5).
    current_limit_a : per-motor current clamp (FACTS §5).
    torque_limit_nm : optional per-wheel torque clamp, applied before the current clamp.
    left_share : fraction of the total torque sent to the left wheel (0.5, FACTS §7).
    use_disturbance_rejection : False = plain LQR (the ESOs keep running for the rates and a
        bumpless switch, but f_hat is not compensated).
    eso_input : 'nominal' (authors) or 'applied' (see module docstring).
    """

    def __init__(self, f_x, f_theta, b_x: float, b_theta: float, *,
                 sample_period_s: float = DEFAULT_SAMPLE_PERIOD_S,
                 eso_omega_o: float | None = None,
                 eso_continuous_gains: Sequence[float] = AUTHORS_CONTINUOUS_GAINS,
                 eso_method: str = 'current',
                 f_limit_x: float | None = None, f_limit_theta: float | None = None,
                 torque_constant_nm_per_a: float = DEFAULT_TORQUE_CONSTANT_NM_PER_A,
                 gear_ratio: float = DEFAULT_GEAR_RATIO,
                 current_limit_a: float = DEFAULT_CURRENT_LIMIT_A,
                 torque_limit_nm: float | None = None,
                 left_share: float = 0.5,
                 use_disturbance_rejection: bool = True,
                 eso_input: str = 'nominal'):
        if eso_input not in ('nominal', 'applied'):
            raise ValueError("eso_input must be 'nominal' or 'applied'")
        if not 0.0 <= left_share <= 1.0:
            raise ValueError('left_share must be in [0, 1]')
        if torque_constant_nm_per_a <= 0 or gear_ratio <= 0 or current_limit_a <= 0:
            raise ValueError('motor constants and current limit must be positive')
        self.h = float(sample_period_s)
        self.kt = float(torque_constant_nm_per_a)
        self.gear = float(gear_ratio)
        self.current_limit = float(current_limit_a)
        self.torque_limit = None if torque_limit_nm is None else abs(float(torque_limit_nm))
        self.left_share = float(left_share)
        self.use_disturbance_rejection = bool(use_disturbance_rejection)
        self.eso_input = eso_input
        gains = None if eso_omega_o is not None else eso_continuous_gains
        self.eso_x = ExtendedStateObserver(b_x, self.h, omega_o=eso_omega_o, continuous_gains=gains,
                                           method=eso_method, f_limit=f_limit_x)
        self.eso_theta = ExtendedStateObserver(b_theta, self.h, omega_o=eso_omega_o,
                                               continuous_gains=gains, method=eso_method,
                                               f_limit=f_limit_theta)
        self.set_gains(f_x, f_theta, b_x, b_theta)
        self._u_prev_x = 0.0
        self._u_prev_theta = 0.0
        self._ready = False

    @classmethod
    def from_design(cls, design: Mapping, **kwargs) -> 'AdrcController':
        """Build from a ``GainCache.design(...)`` dict."""
        return cls(design['F_x'], design['F_theta'], design['b_x'], design['b_theta'], **kwargs)

    # ------------------------------------------------------------------ configuration
    def set_gains(self, f_x, f_theta, b_x: float, b_theta: float) -> None:
        """New LQR(q) design (pose or beta changed); observer estimates are kept."""
        if b_x == 0 or b_theta == 0:
            raise ValueError('b_x and b_theta must be non-zero')
        self.f_x = np.asarray(f_x, float).ravel()
        self.f_theta = np.asarray(f_theta, float).ravel()
        if self.f_x.size != 2 or self.f_theta.size != 2:
            raise ValueError('F_x and F_theta must have 2 elements each')
        self.b_x = float(b_x)
        self.b_theta = float(b_theta)
        self.eso_x.set_b(self.b_x)
        self.eso_theta.set_b(self.b_theta)

    def set_disturbance_rejection(self, enabled: bool) -> None:
        """Switch between ADRC (True) and plain LQR (False) for comparisons."""
        self.use_disturbance_rejection = bool(enabled)

    @property
    def motor_torque_per_amp(self) -> float:
        """Wheel torque per motor ampere: gear ratio x torque constant."""
        return self.gear * self.kt

    # ------------------------------------------------------------------ running
    def reset(self, measurement) -> None:
        """Initialise both ESOs from a measurement: mapping with theta, x (and optional dtheta,
        dx) or a sequence (theta, x[, dtheta, dx])."""
        if isinstance(measurement, Mapping):
            theta = measurement['theta']
            x = measurement['x']
            dtheta = measurement.get('dtheta', 0.0) or 0.0
            dx = measurement.get('dx', 0.0) or 0.0
        else:
            vals = list(measurement) + [0.0, 0.0]
            theta, x, dtheta, dx = vals[:4]
        self.eso_theta.reset(theta, dtheta)
        self.eso_x.reset(x, dx)
        self._u_prev_x = 0.0
        self._u_prev_theta = 0.0
        self._ready = True

    def update(self, theta: float, x: float, dt: float | None = None, *,
               dtheta: float | None = None, dx: float | None = None) -> WheelCommand:
        """One control step from the measured CoM angle theta [rad] and wheel position x.

        dt: the period since the previous call (None = nominal). dtheta, dx: measured rates
        (used in the feedback when given; else the ESO estimates).
        """
        if not self._ready:
            self.reset({'theta': theta, 'x': x, 'dtheta': dtheta, 'dx': dx})
        zx = self.eso_x.update(x, self._u_prev_x, dt)
        zt = self.eso_theta.update(theta, self._u_prev_theta, dt)
        vx = zx[1] if dx is None else float(dx)
        vt = zt[1] if dtheta is None else float(dtheta)
        u_x = -float(self.f_x @ np.array([x, vx]))
        u_th = -float(self.f_theta @ np.array([theta, vt]))
        if self.use_disturbance_rejection:
            tx = u_x - zx[2] / self.b_x
            tt = u_th - zt[2] / self.b_theta
        else:
            tx, tt = u_x, u_th
        tau_cmd = tx + tt
        tau_l, tau_r, i_l, i_r, sat = self._to_wheels(tau_cmd)
        tau_total = tau_l + tau_r
        if self.eso_input == 'nominal':
            self._u_prev_x, self._u_prev_theta = u_x, u_th
        else:
            scale = tau_total / tau_cmd if tau_cmd != 0 else 1.0
            self._u_prev_x, self._u_prev_theta = tx * scale, tt * scale
        return WheelCommand(tau_l, tau_r, i_l, i_r, tau_total, u_x, u_th, float(zx[2]),
                            float(zt[2]), sat)

    def _to_wheels(self, tau_total: float):
        """Split, limit torque, convert to current, limit current, and report what is applied."""
        k = self.motor_torque_per_amp
        taus = [self.left_share * tau_total, (1.0 - self.left_share) * tau_total]
        sat = False
        out_tau, out_i = [], []
        for tau in taus:
            if self.torque_limit is not None and abs(tau) > self.torque_limit:
                tau = float(np.sign(tau)) * self.torque_limit
                sat = True
            i = tau / k
            if abs(i) > self.current_limit:
                i = float(np.sign(i)) * self.current_limit
                sat = True
            out_i.append(i)
            out_tau.append(i * k)
        return out_tau[0], out_tau[1], out_i[0], out_i[1], sat
