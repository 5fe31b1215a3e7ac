"""Where the robot really balances, from an ESO: the disturbance of a wrong CoM, rejected through the lean.

A wrong CoM estimate is, to the controller, a constant disturbance torque about the axle (paper §II-D).
The paper's law cancels the estimated disturbance in the wheel torque, but a static torque about the axle
cannot be cancelled by the wheels of a pendulum: at rest the wheel torque must be zero and the true CoM
must be over the axle. So that law, like plain LQR, comes to rest at theta = delta (the CoM-angle error)
and pays for it with a position offset x - x_ref = -F_theta0 delta / F_x0 (10.3 m per rad in the Table II
pose; docs/control.md). The one place to reject this disturbance is the balance point itself.

This observer is an ESO on the theta channel with the LQR(q) linear model as its known part,

    theta'' = a theta + a_dx x' + a_dth theta' + b tau + f      (theta = 0: the model's balance),

fed with the applied torque. The plant differs from the model by f = -a delta at rest (exactly, whatever
the control does), so delta_hat = -f_hat / a, low-pass filtered over `time_constant_s` and limited to
`limit_rad`. The controller regulates theta - delta_hat instead of theta: it comes to rest at x_ref with
the true CoM over the axle. The filter keeps this trim slow next to the balance dynamics (the ESO itself
runs at the ADRC's bandwidth), so the LQR(q) design is not disturbed.
"""
from __future__ import annotations

import math

from .eso import ExtendedStateObserver


class BalancePointObserver:
    """delta_hat: the CoM-angle error of the current beta at the current pose (rad)."""

    def __init__(self, h: float, omega_o: float, time_constant_s: float = 1.0, limit_rad: float = 0.3):
        if time_constant_s <= 0 or limit_rad <= 0:
            raise ValueError('time_constant_s and limit_rad must be positive')
        self.eso = ExtendedStateObserver(1.0, h, omega_o=omega_o)      # its design; the state is ours:
        self.z = [0.0, 0.0, 0.0]               # theta_hat, theta_dot_hat, f_hat as floats (a 500 Hz loop)
        self.time_constant = float(time_constant_s)
        self.limit = float(limit_rad)
        self.a = self.a_dx = self.a_dth = 0.0
        self.b = 1.0
        self.delta = 0.0
        self._u_prev = 0.0
        self._floats = {}

    def set_model(self, a, b) -> None:
        """The linearisation of the current pose and beta (``GainCache.design``'s 'A' and 'B')."""
        if b[3] == 0 or a[3][2] == 0:
            raise ValueError('the theta channel needs non-zero gravity and input terms')
        self.a_dx, self.a, self.a_dth = float(a[3][1]), float(a[3][2]), float(a[3][3])
        if float(b[3]) != self.b:
            self.b = float(b[3])
            self.eso.set_b(self.b)
            self._floats.clear()

    def reset(self, theta: float, dtheta: float) -> None:
        """Start at BALANCE entry, assuming the model right (delta_hat = 0)."""
        self.z = [float(theta), float(dtheta), 0.0]
        self.delta = 0.0
        self._u_prev = 0.0

    def shift(self, delta_offset: float, same_pose: bool) -> None:
        """The model's theta offset moved by `delta_offset`: the measured theta jumps with no motion.
        A new beta at the same pose moves the error by as much (the true balance pitch stays); at a new
        pose the best guess is that the CoM-angle error stays what it was."""
        z = self.z
        z[0] += delta_offset
        if same_pose:
            z[2] -= self.a * delta_offset
            self.delta += delta_offset

    def update(self, theta: float, dt: float, hold: bool = False) -> float:
        """One step with the measurement now; returns delta_hat. `hold`: keep delta_hat (the joints move:
        their reaction torques are outside the model and would read as a disturbance)."""
        phi, gam_u, gam_y = self._discretisation(dt)
        z0, z1, z2 = self.z
        u, y = self._u_prev, theta
        f = phi[6] * z0 + phi[7] * z1 + phi[8] * z2 + gam_u[2] * u + gam_y[2] * y
        self.z = [phi[0] * z0 + phi[1] * z1 + phi[2] * z2 + gam_u[0] * u + gam_y[0] * y,
                  phi[3] * z0 + phi[4] * z1 + phi[5] * z2 + gam_u[1] * u + gam_y[1] * y, f]
        if not hold:
            target = -f / self.a
            self.delta += (1.0 - math.exp(-dt / self.time_constant)) * (target - self.delta)
            self.delta = max(-self.limit, min(self.limit, self.delta))
        return self.delta

    def applied(self, tau: float, theta: float, dx: float, dtheta: float) -> None:
        """The torque applied from this step on, with the state it was applied in (held over the period):
        the ESO's input is the model's whole known part, in units of torque."""
        self._u_prev = tau + (self.a * theta + self.a_dx * dx + self.a_dth * dtheta) / self.b

    def _discretisation(self, dt: float):
        key = round(dt, 6)
        d = self._floats.get(key)
        if d is None:
            m = self.eso.discretisation(dt)
            d = (tuple(float(v) for v in m.phi.ravel()), tuple(float(v) for v in m.gam_u),
                 tuple(float(v) for v in m.gam_y))
            if len(self._floats) > 64:
                self._floats.clear()
            self._floats[key] = d
        return d
