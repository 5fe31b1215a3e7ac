"""The robot as a wheeled inverted pendulum: reduction of locked poses, dynamics, linearisation.

This module is the one statement of the WIP physics. The reduced plant (krang_sim.reduced_plant),
the controller's design (``linearize``), the discrepancy replay and its named effects
(krang_model.effects) all evaluate ``WipDynamics`` and step it with its one integrator
(``step_pitch``; the replay's batches with ``PitchBatch``, its in-place form, which
test/test_discrepancy_speed.py holds to it bit for bit); a new physical term is added here (its
parameter in ``krang_model.drivetrain.Drivetrain``, its lines in ``pitch_accelerations`` and in
``PitchBatch.step``) and nowhere else.

With the body joints locked the robot is one rigid body on two wheels. Its state is the
ground-referenced wheel angle phi (x = r phi, as the hardware's "x_wheel = encoders + IMU
pitch"), the base pitch q_base (the IMU pitch; krang_model/README.md, Conventions) and the yaw
psi. The body CoM angle from vertical is theta = q_base + offset, where the offset is fixed by the
pose and beta.

Equations (Lagrange, plus rotor inertia as in the hardware's linearize_wip.cpp,
plus a floor slope alpha and a caster contact):
  [(M+m_w) r^2 + I_w + J] phi'' + [M r l cos(theta+alpha) - J] theta''
      = M r l sin(theta+alpha) theta'^2 - (M+m_w) g r sin(alpha) + tau
        - b (phi'-theta') - b_g phi' - tau_c
  [M r l cos(theta+alpha) - J] phi'' + [I_axle + J] theta''
      = M g l sin(theta) - tau + b (phi'-theta') + tau_caster
with J = 2 gear^2 I_rotor the reflected rotor inertia of both drives, tau the sum of the wheel
torques and tau_c the wheels' Coulomb friction.

Broadcasting. Every field of a ``WipBody`` and of a ``Drivetrain`` may be a float or a numpy array,
and so may the state and the torques: a batch of poses, of parameter sets (one per row of a fit)
and of states steps in one call. Python floats take the ``math`` path, which keeps one simulator
step near a microsecond; arrays take the numpy path. Both paths run the same lines.
"""

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from .kinematics import body_placements


@dataclass(frozen=True)
class WipBody:
    """A locked pose reduced to one rigid body on the axle (the wheels excluded).

    Fields are floats for one pose or arrays for a batch (``body[i]`` is pose i)."""

    mass: float  # kg
    com_distance: float  # m, axle to body CoM
    com_offset: float  # rad, theta (CoM angle from vertical) = q_base + com_offset
    inertia_axle: float  # kg m^2 about the axle
    # kg m^2 about the vertical through the axle midpoint, wheels included
    yaw_inertia: float = math.nan
    # rad, com_offset of the whole robot incl. wheels (what learning balances)
    com_offset_full: float = math.nan

    def __getitem__(self, i):
        values = np.broadcast_arrays(
            *(np.asarray(getattr(self, f.name), float) for f in fields(self))
        )
        return WipBody(*(float(v[i]) for v in values))

    def __len__(self):
        return int(np.size(self.com_offset))

    def adjusted(self, com_shift=0.0, inertia_add=0.0):
        """The body with its CoM moved `com_shift` (m) farther from the axle along its direction
        (a point-mass shift: M l -> M (l + dl), I += M ((l + dl)^2 - l^2)) and `inertia_add`
        (kg m^2) more inertia about the axle: the named effects com_height and body_inertia."""
        dist, m = self.com_distance, self.mass
        return replace(
            self,
            com_distance=dist + com_shift,
            inertia_axle=self.inertia_axle + inertia_add + m * com_shift * (2 * dist + com_shift),
        )


def reduce_poses(robot, joints, beta):
    """WipBody of N locked poses (rows of `joints`, pose order) under mass parameters beta: fields
    are (N,) arrays."""
    rot, trans = body_placements(robot, np.atleast_2d(np.asarray(joints, dtype=float)))
    return reduce_placements(robot, rot, trans, beta)


def reduce_pose(robot, joints, beta):
    """WipBody of one locked pose: ``reduce_poses(robot, [joints], beta)[0]``."""
    return reduce_poses(robot, np.asarray(joints, dtype=float)[None], beta)[0]


def reduce_placements(robot, rot, trans, beta):
    """WipBody from body placements (rot (N, B, 3, 3), trans (N, B, 3) in the base frame, as
    ``kinematics.body_placements`` gives them): a caller that varies beta at fixed poses (a payload
    being fitted) computes the kinematics once."""
    # explicit products and sums (no einsum): a pose's result must not depend on the batch it is in
    b4 = np.asarray(beta, dtype=float).reshape(-1, 4)
    m_all = b4[:, 0]
    local = np.divide(
        b4[:, 1:], m_all[:, None], out=np.zeros((len(b4), 3)), where=m_all[:, None] != 0
    )
    com_all = trans + _matvec(rot, local)  # (N, B, 3) body CoMs
    wheels = list(robot.wheel_body_ids)
    ids = [i for i in range(robot.n_bodies) if i not in wheels]
    m, com, rot_b = m_all[ids], com_all[:, ids], rot[:, ids]
    moment = _sum_bodies(m[:, None] * com)
    moment_full = moment + _sum_bodies(m_all[wheels, None] * com_all[:, wheels])
    inert = robot.body_inertias[ids]  # (B, 3, 3) about each CoM
    mass = float(m.sum())
    my, mz = moment[:, 1], moment[:, 2]
    offset = np.arctan2(-mz, my)
    # about the axle (base x): rotational part plus the parallel-axis term
    axle = _quadratic(inert, rot_b[..., 0, :])  # base x in body coordinates = row 0 of R
    inertia_axle = _sum_bodies(axle + m * (com[..., 1] ** 2 + com[..., 2] ** 2))
    # yaw inertia at balance (theta = 0): frame-0 x = (0, sin o, -cos o) and z = (0, cos o, sin o)
    # in base coordinates, with o = -offset the balance pitch
    s, c = np.sin(-offset)[:, None], np.cos(-offset)[:, None]
    x0 = s * com[..., 1] - c * com[..., 2]
    # frame-0 z in body coordinates
    vertical = c[..., None] * rot_b[..., 1, :] + s[..., None] * rot_b[..., 2, :]
    yaw = _sum_bodies(_quadratic(inert, vertical) + m * (x0**2 + com[..., 0] ** 2))
    for i in wheels:
        yaw = yaw + (robot.body_inertias[i][1, 1] + m_all[i] * trans[:, i, 0] ** 2)
    return WipBody(
        mass=np.full(len(offset), mass),
        com_distance=np.hypot(my, mz) / mass,
        com_offset=offset,
        inertia_axle=inertia_axle,
        yaw_inertia=yaw,
        com_offset_full=np.arctan2(-moment_full[:, 2], moment_full[:, 1]),
    )


def _sum_bodies(x):
    """Sum over axis 1 in body order (numpy's own sum changes its order with the batch size)."""
    out = x[:, 0].copy()
    for b in range(1, x.shape[1]):
        out += x[:, b]
    return out


def _matvec(rot, v):
    """rot (..., 3, 3) @ v (..., 3), summed term by term."""
    return (
        rot[..., 0] * v[..., 0, None]
        + rot[..., 1] * v[..., 1, None]
        + rot[..., 2] * v[..., 2, None]
    )


def _quadratic(inertia, u):
    """u^T I u for inertias (B, 3, 3) and directions u (N, B, 3), summed term by term."""
    iu = _matvec(inertia, u)
    return u[..., 0] * iu[..., 0] + u[..., 1] * iu[..., 1] + u[..., 2] * iu[..., 2]


def point_mass_beta(robot, beta, body, point, kg):
    """beta with `kg` more mass at `point` (m, in the frame of `body`): an unmodelled payload."""
    beta = np.array(beta, dtype=float)
    if kg:
        i = robot.body_names.index(body)
        beta[4 * i] += kg
        beta[4 * i + 1 : 4 * i + 4] += kg * np.asarray(point, dtype=float)
    return beta


_ndarray = np.ndarray


def _is_array(*xs):
    return any(isinstance(x, np.ndarray) for x in xs)


def _nonzero(x):
    return bool(np.any(x)) if isinstance(x, np.ndarray) else x != 0.0


class WipDynamics:
    """The nonlinear WIP with caster contact: the one implementation of the equations above.

    State: [phi, q_base, phi', q_base', psi, psi'] (phi: ground-referenced wheel angle, psi: yaw).
    Inputs: left and right wheel torques at the wheels (N m, after the gearbox). `body` and `drive`
    may hold arrays (poses, parameter sets); everything broadcasts against the state.
    """

    def __init__(self, body, drive):
        self.body = body
        self.drive = d = drive
        sin = np.sin if _is_array(d.floor_slope) else math.sin
        self._j = d.reflected_rotor_inertia
        self._m11 = (body.mass + d.wheel_mass) * d.wheel_radius**2 + d.wheel_inertia + self._j
        self._mrl = body.mass * d.wheel_radius * body.com_distance
        self._m22 = body.inertia_axle + self._j
        self._mgl = body.mass * d.gravity * body.com_distance
        self._grade = (body.mass + d.wheel_mass) * d.gravity * d.wheel_radius * sin(d.floor_slope)
        half = 0.5 * d.track_width / d.wheel_radius
        self._yaw_inertia = body.yaw_inertia + 2.0 * (d.wheel_inertia / 2 + self._j / 2) * half**2
        self._yaw_arm = 0.5 * d.track_width / d.wheel_radius
        self._coulomb = _nonzero(d.coulomb_friction)
        self._caster_pitch = d.caster_contact_pitch
        self._numpy = _is_array(self._mrl, self.body.com_offset, d.floor_slope, d.coulomb_friction)

    def caster_torque(self, q_base, dq_base):
        """The caster's unilateral penalty torque on the body (zero out of contact), at the pitch
        the caster geometry, the wheel radius and the floor slope give
        (``Drivetrain.caster_contact_pitch``)."""
        d = self.drive
        pen = self._caster_pitch - q_base
        if type(pen) is not _ndarray:
            if pen <= 0.0:
                return 0.0
            return max(0.0, d.caster_stiffness * pen - d.caster_damping * dq_base)
        touching = pen > 0.0
        if not touching.any():
            return 0.0
        return np.where(
            touching, np.maximum(0.0, d.caster_stiffness * pen - d.caster_damping * dq_base), 0.0
        )

    def pitch_accelerations(self, q_base, dphi, dq_base, tau, f_phi=None, f_qbase=None):
        """(phi'', q_base'') under the total wheel torque `tau`, plus optional extra generalised
        forces on the wheel and the pitch equations (N m)."""
        d = self.drive
        if (
            self._numpy
            or type(q_base) is _ndarray
            or type(dphi) is _ndarray
            or type(dq_base) is _ndarray
            or type(tau) is _ndarray
        ):
            sin, cos, tanh = np.sin, np.cos, np.tanh
        else:
            sin, cos, tanh = math.sin, math.cos, math.tanh
        theta = q_base + self.body.com_offset
        c = cos(theta + d.floor_slope)
        s_slope = sin(theta + d.floor_slope)
        rel = dphi - dq_base
        # the wheels' friction against the body is a torque between the two, like the motors':
        # it enters the wheel and the pitch equations with opposite signs
        internal = d.viscous_friction * rel
        if self._coulomb:
            internal = internal + 2.0 * d.coulomb_friction * tanh(rel / 1e-2)
        m12 = self._mrl * c - self._j
        f1 = (
            self._mrl * s_slope * dq_base * dq_base
            - self._grade
            + tau
            - internal
            - d.ground_viscous * dphi
        )
        f2 = self._mgl * sin(theta) - tau + internal + self.caster_torque(q_base, dq_base)
        if f_phi is not None:
            f1 = f1 + f_phi
            f2 = f2 + f_qbase
        delta = self._m11 * self._m22 - m12 * m12
        return (self._m22 * f1 - m12 * f2) / delta, (self._m11 * f2 - m12 * f1) / delta

    def yaw_acceleration(self, dpsi, tau_left, tau_right):
        """psi'' under the given wheel torques (the yaw is decoupled from the pitch plane)."""
        return (
            (tau_right - tau_left) * self._yaw_arm - self.drive.yaw_friction * dpsi
        ) / self._yaw_inertia

    def accelerations(self, state, tau_left, tau_right):
        """(phi'', q_base'', psi'') at `state` under the given wheel torques."""
        phi, qb, dphi, dqb, psi, dpsi = state
        ddphi, ddqb = self.pitch_accelerations(qb, dphi, dqb, tau_left + tau_right)
        return ddphi, ddqb, self.yaw_acceleration(dpsi, tau_left, tau_right)

    def energy(self, state):
        """Kinetic + potential energy (J), for conservation checks (slope and caster excluded)."""
        phi, qb, dphi, dqb, psi, dpsi = state
        cos = np.cos if self._numpy or _is_array(qb) else math.cos
        theta = qb + self.body.com_offset
        kinetic = (
            0.5 * self._m11 * dphi**2
            + (self._mrl * cos(theta) - self._j) * dphi * dqb
            + 0.5 * self._m22 * dqb**2
            + 0.5 * self._yaw_inertia * dpsi**2
        )
        return kinetic + self._mgl * cos(theta)

    def step_pitch(self, phi, q_base, dphi, dq_base, tau, dt, f_phi=None, f_qbase=None):
        """One step of the pitch plane: (phi, q_base, phi', q_base') after `dt` under the total
        wheel torque `tau` (and optional extra generalised forces, as ``pitch_accelerations``).
        The one integrator of the model: semi-implicit Euler (velocities first), symplectic, one
        force evaluation per step. Floats (a simulator step) or arrays (the replay: every window
        and every parameter set at once)."""
        ddphi, ddqb = self.pitch_accelerations(q_base, dphi, dq_base, tau, f_phi, f_qbase)
        dphi = dphi + dt * ddphi
        dq_base = dq_base + dt * ddqb
        return phi + dt * dphi, q_base + dt * dq_base, dphi, dq_base

    def step(self, state, tau_left, tau_right, dt):
        """One step of the whole state: ``step_pitch`` and the decoupled yaw, integrated alike."""
        phi, qb, dphi, dqb, psi, dpsi = state
        phi, qb, dphi, dqb = self.step_pitch(phi, qb, dphi, dqb, tau_left + tau_right, dt)
        dpsi = dpsi + dt * self.yaw_acceleration(dpsi, tau_left, tau_right)
        return [phi, qb, dphi, dqb, psi + dt * dpsi, dpsi]

    def step_rk4(self, state, tau_left, tau_right, dt):
        """Classical RK4 (four force evaluations) for accuracy checks."""

        def f(s):
            a = self.accelerations(s, tau_left, tau_right)
            return [s[2], s[3], a[0], a[1], s[5], a[2]]

        k1 = f(state)
        k2 = f([x + 0.5 * dt * k for x, k in zip(state, k1)])
        k3 = f([x + 0.5 * dt * k for x, k in zip(state, k2)])
        k4 = f([x + dt * k for x, k in zip(state, k3)])
        return [
            x + dt / 6.0 * (a + 2 * b + 2 * c + d) for x, a, b, c, d in zip(state, k1, k2, k3, k4)
        ]

    def wheel_torques_from_currents(self, current_left, current_right):
        """Motor currents (A, clamped at the limit) to wheel torques (N m)."""
        d = self.drive
        k = d.torque_constant * d.gear_ratio
        lim = d.current_limit
        return k * min(max(current_left, -lim), lim), k * min(max(current_right, -lim), lim)


class PitchBatch:
    """``WipDynamics.step_pitch`` for large batches (the replay: parameter sets x windows): the
    same accelerations and the same semi-implicit Euler, in place on (P, S) arrays, with the terms
    that stay fixed along a horizon computed once (per body change) and no temporaries. In numpy's
    float64 path a sine or cosine costs about 50 multiplies, so the CoM angle's sine and cosine are
    carried by rotation through each step's angle increment (``_rotate``) and recomputed exactly
    every ``anchor`` steps; with ``anchor=1`` every step is bit-identical to ``step_pitch``,
    otherwise they agree to rounding (1e-14). Extra generalised forces are added as in
    ``pitch_accelerations``.

    ``set_body(body)`` (a ``WipBody`` of arrays broadcasting to the batch) before the first step
    and whenever the body changes; ``start(q_base)`` sets the trigonometric state;
    ``step(phi, q_base, dphi, dq_base, tau, dt, f_phi, f_qbase)`` updates the four state arrays in
    place."""

    def __init__(self, shape, drive, anchor: int = 16):
        self.drive = d = drive
        self.shape = shape
        self.anchor = max(1, int(anchor))
        self._j = d.reflected_rotor_inertia
        self._slope = _nonzero(d.floor_slope)
        self._coulomb = _nonzero(d.coulomb_friction)
        self._ground = _nonzero(d.ground_viscous)
        self._cf2 = 2.0 * d.coulomb_friction
        self._cp = d.caster_contact_pitch
        self._cp_max = float(np.max(self._cp))
        buf = lambda: np.empty(shape)  # noqa: E731
        self._s, self._c = buf(), buf()
        self._s2, self._c2 = (buf(), buf()) if self._slope else (self._s, self._c)
        self._rel, self._fr, self._m12, self._f1, self._f2 = buf(), buf(), buf(), buf(), buf()
        self._a, self._b, self._dl = buf(), buf(), buf()
        self._mask = np.empty(shape, bool)
        self._off = None
        self._steps = 0

    def set_body(self, body):
        """The body terms (``WipDynamics.__init__``'s) for the coming steps; the CoM angle's
        trigonometric state follows a change of the body's CoM offset."""
        d = self.drive
        mass = body.mass
        self._m11 = (mass + d.wheel_mass) * d.wheel_radius**2 + d.wheel_inertia + self._j
        self._mrl = mass * d.wheel_radius * body.com_distance
        self._m22 = body.inertia_axle + self._j
        self._mgl = mass * d.gravity * body.com_distance
        sin = np.sin if _is_array(d.floor_slope) else math.sin
        self._grade = (mass + d.wheel_mass) * d.gravity * d.wheel_radius * sin(d.floor_slope)
        self._m11m22 = self._m11 * self._m22
        off = np.broadcast_to(np.asarray(body.com_offset, float), self.shape)
        if self._off is not None:
            self._rotate(off - self._off)
        self._off = np.array(off)

    def start(self, q_base):
        """The trigonometric state at the initial pitch (after ``set_body``)."""
        self._exact(q_base)
        self._steps = 0

    def _exact(self, q_base):
        th = np.add(q_base, self._off, out=self._a)
        if self._slope:
            tha = np.add(th, self.drive.floor_slope, out=self._b)
            np.sin(tha, out=self._s2)
            np.cos(tha, out=self._c2)
        np.cos(th, out=self._c)
        np.sin(th, out=self._s)

    def _rotate(self, delta):
        """Advance the sines and cosines by the angle increments `delta`: Taylor series to the
        6th order, off by less than 5e-15 for increments up to 0.03 rad (a pitch rate of 15 rad/s
        over a 2 ms step) and 1e-11 up to 0.09 rad, until the next exact anchor. Each element's
        result depends on its own increment alone, not on the batch it is in."""
        d2 = np.multiply(delta, delta, out=self._dl)
        sd = np.multiply(d2, 1.0 / 120.0, out=self._a)
        sd -= 1.0 / 6.0
        sd *= d2
        sd += 1.0
        sd *= delta  # sin(delta)
        cm = np.multiply(d2, -1.0 / 720.0, out=self._b)
        cm += 1.0 / 24.0
        cm *= d2
        cm -= 0.5
        cm *= d2  # cos(delta) - 1
        pairs = [(self._s, self._c)] + ([(self._s2, self._c2)] if self._slope else [])
        for s, c in pairs:
            ns = np.multiply(s, cm, out=self._rel)
            ns += np.multiply(c, sd, out=self._m12)
            nc = np.multiply(c, cm, out=self._fr)
            nc -= np.multiply(s, sd, out=self._m12)
            s += ns
            c += nc

    def step(self, phi, q_base, dphi, dq_base, tau, dt, f_phi=None, f_qbase=None):
        d = self.drive
        if self._steps % self.anchor == 0:
            self._exact(q_base)
        self._steps += 1
        rel = np.subtract(dphi, dq_base, out=self._rel)
        internal = np.multiply(rel, d.viscous_friction, out=self._fr)
        if self._coulomb:
            t = np.divide(rel, 1e-2, out=self._a)
            np.tanh(t, out=t)
            t *= self._cf2
            internal += t
        m12 = np.multiply(self._mrl, self._c2, out=self._m12)
        m12 -= self._j
        f1 = np.multiply(self._mrl, self._s2, out=self._f1)
        f1 *= dq_base
        f1 *= dq_base
        f1 -= self._grade
        f1 += tau
        f1 -= internal
        if self._ground:
            f1 -= np.multiply(dphi, d.ground_viscous, out=self._a)
        f2 = np.multiply(self._mgl, self._s, out=self._f2)
        f2 -= tau
        f2 += internal
        if q_base.min() < self._cp_max:  # somewhere on the caster (cp - q > 0 iff q < cp)
            pen = np.subtract(self._cp, q_base, out=self._a)
            touching = np.greater(pen, 0.0, out=self._mask)
            ct = np.multiply(pen, d.caster_stiffness, out=self._a)
            ct -= np.multiply(dq_base, d.caster_damping, out=self._b)
            np.maximum(ct, 0.0, out=ct)
            ct *= touching
            f2 += ct
        if f_phi is not None:
            f1 += f_phi
            f2 += f_qbase
        delta = np.multiply(m12, m12, out=self._a)
        np.subtract(self._m11m22, delta, out=delta)
        dd = np.multiply(self._m22, f1, out=self._b)
        dd -= np.multiply(m12, f2, out=self._dl)
        dd /= delta
        dd *= dt
        dphi += dd
        dd = np.multiply(f2, self._m11, out=self._b)
        dd -= np.multiply(m12, f1, out=self._dl)
        dd /= delta
        dd *= dt
        dq_base += dd
        phi += np.multiply(dphi, dt, out=self._a)
        inc = np.multiply(dq_base, dt, out=self._f1)
        q_base += inc
        if (self._steps % self.anchor) != 0:
            self._rotate(inc)


#: step of the central differences in ``linearize`` (rad, rad/s, N m): the model is linear in the
#: velocities and the torque, quadratic in theta' and sin/cos in theta, so at this step the
#: truncation error (h^2/6 relative) is below rounding
_LINEARIZE_STEP = 1e-7


def linearize(body, drive):
    """Continuous A (4x4), B (4x1) about upright balance at rest; state [x, x', theta, theta'],
    input the total wheel torque tau_w (N m): the paper's (A(q), B(q)), B = [0, b_x, 0, b_theta].

    The Jacobian of ``WipDynamics.pitch_accelerations`` itself (central differences, exact to
    rounding, see ``_LINEARIZE_STEP``), so every term of the model enters the design; the caster
    is out of contact at upright. Batched bodies or drives give (..., 4, 4) and (..., 4, 1)."""
    dyn = WipDynamics(body, replace(drive, caster_stiffness=0.0, caster_damping=0.0))
    batch = np.broadcast(
        *(
            np.asarray(getattr(body, f.name))
            for f in fields(body)
            if f.name not in ('yaw_inertia', 'com_offset_full')
        ),
        *(np.asarray(getattr(drive, f.name)) for f in fields(drive)),
    ).shape
    h = _LINEARIZE_STEP
    # columns: theta, phi', theta', tau; each at +h and -h
    e = np.zeros((4, 8))
    for k in range(4):
        e[k, 2 * k], e[k, 2 * k + 1] = h, -h
    e = e.reshape(4, 8, *(1,) * len(batch))
    offset = np.asarray(body.com_offset, float)
    q_base = -offset + e[0]
    ddphi, ddqb = dyn.pitch_accelerations(q_base, e[1], e[2], e[3])
    ddphi = np.broadcast_to(ddphi, (8, *batch))
    ddqb = np.broadcast_to(ddqb, (8, *batch))
    # the steps as the model saw them (theta = q_base + offset rounds the step in theta)
    step = np.broadcast_to(e, (4, 8, *batch)).copy()
    step[0] = np.broadcast_to(q_base + offset, (8, *batch))
    step = (step[:, 0::2] - step[:, 1::2])[[0, 1, 2, 3], [0, 1, 2, 3]]  # (4, ...)
    d_phi = (ddphi[0::2] - ddphi[1::2]) / step  # (4, ...) d phi'' / d (theta, phi', theta', tau)
    d_qb = (ddqb[0::2] - ddqb[1::2]) / step
    r = np.asarray(drive.wheel_radius, float)
    zero = np.zeros(batch)
    a = np.stack(
        [
            np.stack([zero, zero + 1.0, zero, zero], axis=-1),
            np.stack([zero, d_phi[1], r * d_phi[0], r * d_phi[2]], axis=-1),
            np.stack([zero, zero, zero, zero + 1.0], axis=-1),
            np.stack([zero, d_qb[1] / r, d_qb[0], d_qb[2]], axis=-1),
        ],
        axis=-2,
    )
    b = np.stack([zero, r * d_phi[3], zero, d_qb[3]], axis=-1)[..., None]
    return a, b
