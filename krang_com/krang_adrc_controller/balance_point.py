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

    def __post_init__(self):
        if self.place_tol_m <= 0 or self.place_speed_m_s <= 0:
            raise ValueError('balance_point.place_tol_m and place_speed_m_s must be positive')
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
    """delta_hat: the CoM-angle error of the current beta at the current pose (rad)."""

    def __init__(self, h: float, omega_o: float, config: ObserverConfig = ObserverConfig()):
        self.eso = ExtendedStateObserver(1.0, h, omega_o=omega_o)
        self.time_constant = float(config.time_constant_s)
        self.limit = float(config.limit_rad)
        self.hold_s = float(config.hold_s)
        self.track_moves = bool(config.track_moves)
        self.converged_tol = float(config.converged_tol_rad)
        self.gap = math.inf  # low-passed (raw estimate - delta_hat), rad
        self.a = self.a_dx = self.a_dth = 0.0
        self.b = 1.0
        self.delta = 0.0
        self._u_prev = 0.0

    def set_model(self, a, b) -> None:
        """The linearisation of the current pose and beta (``GainCache.design``'s 'A' and 'B')."""
        if b[3] == 0 or a[3][2] == 0:
            raise ValueError('the theta channel needs non-zero gravity and input terms')
        self.a_dx, self.a, self.a_dth = float(a[3][1]), float(a[3][2]), float(a[3][3])
        self.b = float(b[3])
        self.eso.set_b(self.b)

    def reset(self, theta: float, dtheta: float) -> None:
        """Start at BALANCE entry, assuming the model right (delta_hat = 0)."""
        self.eso.reset(theta, dtheta)
        self.delta = 0.0
        self.gap = math.inf
        self._u_prev = 0.0

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
            self.delta += delta_offset
        else:
            self.eso.shift(delta_offset)

    def update(self, theta: float, dt: float, hold: bool = False) -> float:
        """One step with the measurement now; returns delta_hat. `hold`: keep delta_hat (the joints
        move: their reaction torques are outside the model and would read as a disturbance)."""
        eso = self.eso
        eso.step(theta, self._u_prev, dt)
        f = eso.z[2]
        if not hold:
            target = -f / self.a
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
