"""Where the robot really balances, from an ESO: the disturbance of a wrong CoM, rejected through
the lean.

A wrong CoM estimate is, to the controller, a constant disturbance torque about the axle (paper
§II-D). The paper's law cancels the estimated disturbance in the wheel torque, but a static torque
about the axle cannot be cancelled by the wheels of a pendulum: at rest the wheel torque must be
zero and the true CoM must be over the axle. So that law, like plain LQR, comes to rest at theta =
delta (the CoM-angle error) and pays for it with a position offset x - x_ref = -F_theta0 delta /
F_x0 (10.3 m per rad in the Table II pose; docs/control.md). The one place to reject this
disturbance is the balance point itself.

This observer is an ESO on the theta channel with the LQR(q) linear model as its known part,

    theta'' = a theta + a_dx x' + a_dth theta' + b tau + f      (theta = 0: the model's balance),

fed with the applied torque. The plant differs from the model by f = -a delta at rest (exactly,
whatever the control does), so delta_hat = -f_hat / a, low-pass filtered over `time_constant_s` and
limited to `limit_rad`. The controller regulates theta - delta_hat instead of theta: it comes to
rest at x_ref with the true CoM over the axle. The filter keeps this trim slow next to the balance
dynamics (the ESO itself runs at the ADRC's bandwidth), so the LQR(q) design is not disturbed.

The drive observer (``drive_observer``). A drive chain the controller is not told (a gearmotor:
0.6-0.8 of the commanded torque, dry friction that sticks below its breakaway torque) is a second
disturbance, and alone the theta channel reads it as CoM error: the trim then swings with the
stick-slip and feeds it (a 180 mrad limit cycle in pitch at 0.75 / 4 N m / 3 N m s, no balanced
point). The two disturbances load the channels differently: a torque about the axle on the body
(CoM error, the arms' reaction) as gravity does, f = -(a_x, a) delta; a torque between wheels and
body (the drive chain's error) as the motors do, f = (b_x, b) drive. A second ESO on the x
channel, fed the same way, gives f_x; the 2 x 2 solve separates delta_hat from drive_hat, and the
controller cancels drive_hat in the wheel torque (a disturbance observer on the drive chain,
limited to ``drive_limit_nm``). On the nominal chain drive_hat stays near zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .eso import ExtendedStateObserver


@dataclass(frozen=True)
class ObserverConfig:
    """The balance-point observer (parameters ``balance_point.*``). The paper's law alone rests
    1.66 m from its reference with a 2.5 cm CoM error; with the observer, within 1 cm
    (docs/control.md)."""

    enabled: bool = field(
        default=True,
        metadata={'doc': "regulate about the estimated balance point (false = the paper's law)"},
    )
    time_constant_s: float = field(
        default=1.0,
        metadata={'doc': 'low-pass of the estimate, s: slow next to the balance dynamics'},
    )
    limit_rad: float = field(
        default=0.3,
        metadata={'doc': '|delta_hat| bound, rad of CoM angle (0.3: ~25 cm of CoM error)'},
    )
    hold_s: float = field(
        default=0.5,
        metadata={
            'doc': 'estimate held while the joints move and this long after, s (the ESO '
            're-converges)'
        },
    )
    track_moves: bool = field(
        default=False,
        metadata={'doc': 'keep estimating while the joints move (false = hold, see hold_s)'},
    )
    converged_tol_rad: float = field(
        default=0.005,
        metadata={
            'doc': 'converged when the low-passed gap between the raw estimate and delta_hat is '
            'below '
            'this, rad (~2.5 mm of CoM at 0.5 m height)'
        },
    )
    place_tol_m: float = field(
        default=0.8,
        metadata={
            'doc': 'while the joints move the estimate counts as converged as long as the robot '
            'stays within this of its position reference, m (and place_speed_m_s)'
        },
    )
    place_speed_m_s: float = field(
        default=0.3,
        metadata={'doc': '... and its ground speed below this, m/s'},
    )
    drive_observer: bool = field(
        default=True,
        metadata={
            'doc': "separate the drive chain's torque error (dry and viscous friction, a torque "
            'shortfall: a torque between wheels and body) from the CoM error with a second '
            'observer on the x channel, and cancel it in the wheel torque (false = every '
            'disturbance reads as CoM error)'
        },
    )
    drive_limit_nm: float = field(
        default=40.0,
        metadata={
            'doc': '|drive torque error| the controller cancels, N m (both wheels): a gearmotor '
            "chain's dry friction (2 x 8 N m) and shortfall, with room"
        },
    )

    def __post_init__(self):
        if self.place_tol_m <= 0 or self.place_speed_m_s <= 0:
            raise ValueError('balance_point.place_tol_m and place_speed_m_s must be positive')
        if self.drive_limit_nm < 0:
            raise ValueError('balance_point.drive_limit_nm must not be negative')
        if (
            self.time_constant_s <= 0
            or self.limit_rad <= 0
            or self.hold_s < 0
            or self.converged_tol_rad <= 0
        ):
            raise ValueError(
                'balance_point.time_constant_s, limit_rad and converged_tol_rad must '
                'be positive, hold_s not negative'
            )


class BalancePointObserver:
    """delta_hat: the CoM-angle error of the current beta at the current pose (rad); with
    ``drive_observer``, also drive_hat: the drive chain's torque error (N m, both wheels)."""

    def __init__(self, h: float, omega_o: float, config: ObserverConfig = ObserverConfig()):
        self.eso = ExtendedStateObserver(1.0, h, omega_o=omega_o)
        self.eso_x = (
            ExtendedStateObserver(1.0, h, omega_o=omega_o) if config.drive_observer else None
        )
        self.time_constant = float(config.time_constant_s)
        self.limit = float(config.limit_rad)
        self.drive_limit = float(config.drive_limit_nm)
        self.hold_s = float(config.hold_s)
        self.track_moves = bool(config.track_moves)
        self.converged_tol = float(config.converged_tol_rad)
        self.gap = math.inf  # low-passed (raw estimate - delta_hat), rad
        self.a = self.a_dx = self.a_dth = 0.0
        self.b = 1.0
        self.ax = self.ax_dx = self.ax_dth = 0.0  # the x row (m/s^2)
        self.bx = 1.0
        self._det = 1.0
        self._split = False  # the drive observer runs (a model with an x channel)
        self.delta = 0.0
        self.raw = 0.0  # the unfiltered estimate of the CoM-angle error, rad
        self.drive = 0.0
        self._u_prev = 0.0
        self._ux_prev = 0.0

    def set_model(self, a, b) -> None:
        """The linearisation of the current pose and beta (``GainCache.design``'s 'A' and 'B')."""
        if b[3] == 0 or a[3][2] == 0:
            raise ValueError('the theta channel needs non-zero gravity and input terms')
        self.a_dx, self.a, self.a_dth = float(a[3][1]), float(a[3][2]), float(a[3][3])
        self.b = float(b[3])
        self.eso.set_b(self.b)
        if self.eso_x is not None:
            self.ax_dx, self.ax, self.ax_dth = float(a[1][1]), float(a[1][2]), float(a[1][3])
            self.bx = float(b[1])
            # f_x = -ax delta + bx drive, f_theta = -a delta + b drive: a torque about the axle
            # on the body (CoM error, the arms' reaction) and one between wheels and body (the
            # drive chain) load the two channels in different proportions
            self._det = self.a * self.bx - self.ax * self.b
            self._split = self.bx != 0 and abs(self._det) > 1e-9 * abs(self.a * self.bx)
            if self._split:  # (a model without an x channel reads every disturbance as delta)
                self.eso_x.set_b(self.bx)

    def reset(
        self, theta: float, dtheta: float, x: float = 0.0, dx: float = 0.0, delta: float = 0.0
    ) -> None:
        """Start (at BALANCE entry, at a stand-up's lift-off) with the CoM-angle error `delta`
        (0: the model right; a failed stand-up's estimate) and no drive torque error."""
        self.eso.reset(theta, dtheta, -self.a * delta)
        if self.eso_x is not None:
            self.eso_x.reset(x, dx, -self.ax * delta if self._split else 0.0)
        self.delta = self.raw = float(delta)
        self.drive = 0.0
        self.gap = math.inf
        self._u_prev = 0.0
        self._ux_prev = 0.0

    @property
    def converged(self) -> bool:
        """delta_hat has caught up with the raw estimate (see ``converged_tol_rad``)."""
        return abs(self.gap) < self.converged_tol

    def shift(self, delta_offset: float, same_pose: bool) -> None:
        """The model's theta offset moved by `delta_offset`: the measured theta jumps with no
        motion. A new beta at the same pose moves the error by as much (the true balance pitch
        stays); at a new pose the best guess is that the CoM-angle error stays what it was."""
        if same_pose:
            self.eso.shift(delta_offset, -self.a * delta_offset)
            if self._split:
                self.eso_x.shift(0.0, -self.ax * delta_offset)
            self.delta += delta_offset
        else:
            self.eso.shift(delta_offset)

    def update(self, theta: float, dt: float, hold: bool = False, x: float = 0.0) -> float:
        """One step with the measurement now; returns delta_hat. `hold`: keep delta_hat (the joints
        move: their reaction torques are outside the model and would read as a disturbance).
        `x`: the position (m), for the drive observer."""
        eso = self.eso
        eso.step(theta, self._u_prev, dt)
        f = eso.z[2]
        ex = self.eso_x
        if not self._split:
            target = -f / self.a
        else:
            ex.step(x, self._ux_prev, dt)
            fx = ex.z[2]
            target = (fx * self.b - f * self.bx) / self._det
            drive = (self.a * fx - self.ax * f) / self._det
            lim = self.drive_limit
            self.drive = -lim if drive < -lim else (lim if drive > lim else drive)
        self.raw = target
        if not hold:
            alpha = 1.0 - math.exp(-dt / self.time_constant)
            gap = target - self.delta
            self.delta += alpha * gap
            self.delta = max(-self.limit, min(self.limit, self.delta))
            self.gap = gap if self.gap == math.inf else self.gap + alpha * (gap - self.gap)
        return self.delta

    def applied(self, tau: float, theta: float, dx: float, dtheta: float) -> None:
        """The torque applied from this step on, with the state it was applied in (held over the
        period): the ESO's input is the model's whole known part, in units of torque."""
        self._u_prev = tau + (self.a * theta + self.a_dx * dx + self.a_dth * dtheta) / self.b
        if self._split:
            self._ux_prev = (
                tau + (self.ax * theta + self.ax_dx * dx + self.ax_dth * dtheta) / self.bx
            )
