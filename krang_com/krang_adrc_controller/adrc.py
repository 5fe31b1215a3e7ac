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
estimates. Motor constants and the current limit come from the one drive-train description
(``krang_model.drivetrain``); everything else is ``AdrcConfig``.

This is the one implementation of the law, and it is the controller's 500 Hz hot path: it runs on
floats (eso.py), because numpy's per-call cost on 2- and 3-vectors would dominate the loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, NamedTuple

from krang_model.drivetrain import Drivetrain

from .eso import EsoConfig, ExtendedStateObserver


@dataclass(frozen=True)
class AdrcConfig:
    """The ADRC law (parameters ``adrc.*``), paper §II-D."""

    use_disturbance_rejection: bool = field(
        default=True,
        metadata={
            'doc': 'false = plain LQR (the observers still run, for the rates and a bumpless '
            'switch)'
        },
    )
    eso_input: str = field(
        default='nominal',
        metadata={
            'doc': "what the ESOs are fed: 'nominal' (the authors' code) or 'applied' (winds up "
            'with a wrong CoM; analysis only)'
        },
    )
    use_measured_rates: bool = field(
        default=True,
        metadata={
            'doc': 'feedback on the IMU rate and the wheel speed (false: on the ESO estimates)'
        },
    )
    f_limit_x: float = field(
        default=0.0, metadata={'doc': '|f_hat| clamp of the x channel, m/s^2 (0 = none)'}
    )
    f_limit_theta: float = field(
        default=0.0, metadata={'doc': '|f_hat| clamp of the theta channel, rad/s^2 (0 = none)'}
    )
    left_share: float = field(
        default=0.5, metadata={'doc': 'fraction of the total wheel torque sent to the left wheel'}
    )
    torque_limit_nm: float = field(
        default=0.0,
        metadata={'doc': 'per-wheel torque clamp before the current clamp, N m (0 = none)'},
    )
    torque_fraction: float = field(
        default=1.0,
        metadata={
            'doc': 'the fraction of the nominal motor torque per ampere the drive chain delivers '
            '(a gearmotor: 0.6-0.8); the controller asks for 1 / fraction more current in every '
            "mode, so its torques and its observers' input gain b0 are the chain's"
        },
    )
    coulomb_compensation_nm: float = field(
        default=0.0,
        metadata={
            'doc': "the drive chain's dry (Coulomb) friction per wheel the controller adds back "
            'in STAND_UP and BALANCE, N m: c tanh(wheel speed / coulomb_speed_rad_s) on each '
            'wheel, from the wheel speed relative to the body (0 = none: the nominal chain; a '
            "gearmotor chain's value comes from `krang discrepancy`'s extended model)"
        },
    )
    coulomb_speed_rad_s: float = field(
        default=0.01,
        metadata={'doc': 'wheel speed at which the compensation reaches 76 % of its value, rad/s'},
    )
    viscous_compensation_nm_s: float = field(
        default=0.0,
        metadata={
            'doc': "the drive chain's viscous friction per wheel beyond the nominal model's, "
            'added back with the dry friction, N m s/rad (0 = none)'
        },
    )
    eso: EsoConfig = EsoConfig()

    def __post_init__(self):
        if not 0.1 <= self.torque_fraction <= 2.0:
            raise ValueError('adrc.torque_fraction must be in [0.1, 2]')
        if self.viscous_compensation_nm_s < 0:
            raise ValueError('adrc.viscous_compensation_nm_s must be >= 0')
        if self.coulomb_compensation_nm < 0 or self.coulomb_speed_rad_s <= 0:
            raise ValueError(
                'adrc.coulomb_compensation_nm must be >= 0 and coulomb_speed_rad_s > 0'
            )
        if self.eso_input not in ('nominal', 'applied'):
            raise ValueError("adrc.eso_input must be 'nominal' or 'applied'")
        if not 0.0 <= self.left_share <= 1.0:
            raise ValueError('adrc.left_share must be in [0, 1]')


class WheelCommand(NamedTuple):
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
    drive : the drive train (gear ratio, torque constant, current limit).
    sample_period_s : nominal loop period; ``update(dt=...)`` re-discretises for others.
    config : the law's settings (``AdrcConfig``, with its ESO design).
    """

    def __init__(
        self,
        f_x,
        f_theta,
        b_x: float,
        b_theta: float,
        drive: Drivetrain,
        *,
        sample_period_s: float,
        config: AdrcConfig = AdrcConfig(),
    ):
        if drive.torque_constant <= 0 or drive.gear_ratio <= 0 or drive.current_limit <= 0:
            raise ValueError('motor constants and current limit must be positive')
        self.h = float(sample_period_s)
        self.config = config
        self.kt = float(drive.torque_constant)
        self.gear = float(drive.gear_ratio)
        self.current_limit = float(drive.current_limit)
        self.torque_limit = abs(float(config.torque_limit_nm)) or None
        self.left_share = float(config.left_share)
        self.use_disturbance_rejection = bool(config.use_disturbance_rejection)
        self.use_measured_rates = bool(config.use_measured_rates)
        self.eso_input = config.eso_input
        self.eso_x = ExtendedStateObserver.from_config(
            b_x, self.h, config.eso, config.f_limit_x or None
        )
        self.eso_theta = ExtendedStateObserver.from_config(
            b_theta, self.h, config.eso, config.f_limit_theta or None
        )
        self.set_gains(f_x, f_theta, b_x, b_theta)
        self._u_prev_x = 0.0
        self._u_prev_theta = 0.0
        self._ready = False

    @classmethod
    def from_design(cls, design: Mapping, drive: Drivetrain, **kwargs) -> 'AdrcController':
        """Build from a ``GainCache.design(...)`` dict."""
        return cls(
            design['F_x'], design['F_theta'], design['b_x'], design['b_theta'], drive, **kwargs
        )

    # ------------------------------------------------------------------ configuration
    def set_gains(self, f_x, f_theta, b_x: float, b_theta: float) -> None:
        """New LQR(q) design (pose or beta changed); observer estimates are kept."""
        if b_x == 0 or b_theta == 0:
            raise ValueError('b_x and b_theta must be non-zero')
        f_x = [float(v) for v in (f_x.ravel() if hasattr(f_x, 'ravel') else f_x)]
        f_theta = [float(v) for v in (f_theta.ravel() if hasattr(f_theta, 'ravel') else f_theta)]
        if len(f_x) != 2 or len(f_theta) != 2:
            raise ValueError('F_x and F_theta must have 2 elements each')
        self.f_x, self.f_theta = tuple(f_x), tuple(f_theta)
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

    def shift_theta(self, step: float) -> None:
        """Bumpless change of the theta origin: a new CoM model moved the measured theta by
        `step` with no motion, which must not read as an acceleration."""
        self.eso_theta.shift(step)

    def update(
        self,
        theta: float,
        x: float,
        dt: float | None = None,
        *,
        dtheta: float | None = None,
        dx: float | None = None,
    ) -> WheelCommand:
        """One control step from the measured CoM angle theta [rad] and wheel position x.

        dt: the period since the previous call (None = nominal). dtheta, dx: measured rates
        (used in the feedback when given and ``use_measured_rates``; else the ESO estimates).
        """
        if not self._ready:
            self.reset({'theta': theta, 'x': x, 'dtheta': dtheta, 'dx': dx})
        eso_x, eso_theta = self.eso_x, self.eso_theta
        eso_x.step(x, self._u_prev_x, dt)
        eso_theta.step(theta, self._u_prev_theta, dt)
        zx, zt = eso_x.z, eso_theta.z
        if self.use_measured_rates and dx is not None:
            vx = dx
        else:
            vx = zx[1]
        if self.use_measured_rates and dtheta is not None:
            vt = dtheta
        else:
            vt = zt[1]
        fx0, fx1 = self.f_x
        ft0, ft1 = self.f_theta
        u_x = -(fx0 * x + fx1 * vx)
        u_th = -(ft0 * theta + ft1 * vt)
        if self.use_disturbance_rejection:
            tx = u_x - zx[2] / self.b_x
            tt = u_th - zt[2] / self.b_theta
        else:
            tx, tt = u_x, u_th
        tau_cmd = tx + tt
        # split, limit the torque, convert to current, limit the current
        k = self.gear * self.kt
        lim = self.current_limit
        tlim = self.torque_limit
        sat = False
        tau_l = self.left_share * tau_cmd
        tau_r = (1.0 - self.left_share) * tau_cmd
        if tlim is not None:
            if abs(tau_l) > tlim:
                tau_l, sat = math.copysign(tlim, tau_l), True
            if abs(tau_r) > tlim:
                tau_r, sat = math.copysign(tlim, tau_r), True
        i_l = tau_l / k
        i_r = tau_r / k
        if abs(i_l) > lim:
            i_l, sat = math.copysign(lim, i_l), True
        if abs(i_r) > lim:
            i_r, sat = math.copysign(lim, i_r), True
        tau_l, tau_r = i_l * k, i_r * k
        tau_total = tau_l + tau_r
        if self.eso_input == 'nominal':
            self._u_prev_x, self._u_prev_theta = u_x, u_th
        else:
            scale = tau_total / tau_cmd if tau_cmd != 0 else 1.0
            self._u_prev_x, self._u_prev_theta = tx * scale, tt * scale
        return WheelCommand(tau_l, tau_r, i_l, i_r, tau_total, u_x, u_th, zx[2], zt[2], sat)


def drive_chain_overrides(drive: Drivetrain, nominal: Drivetrain) -> dict:
    """The controller parameters for a drive chain that differs from the nominal one (e.g. the
    ``ModelTerms.drive`` of an extended model of `krang discrepancy`): its torque fraction, its
    dry friction and its viscous friction beyond the nominal's; with dry friction, a slower
    balance-point trim (``balance_point.time_constant_s``, 4 s). The shipped controller runs an
    untold chain of this range too (its drive observer, balance_point.py); told, it need not
    observe what it knows."""
    out = {
        'adrc.torque_fraction': float(drive.torque_constant / nominal.torque_constant),
        'adrc.coulomb_compensation_nm': float(drive.coulomb_friction),
        'adrc.viscous_compensation_nm_s': float(
            max(drive.viscous_friction - nominal.viscous_friction, 0.0)
        ),
    }
    if drive.coulomb_friction > 0:
        out['balance_point.time_constant_s'] = 4.0
    return out
