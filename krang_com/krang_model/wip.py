"""The robot as a wheeled inverted pendulum: reduction of locked poses, dynamics, linearisation.

This module is the one statement of the WIP physics. The reduced plant (krang_sim.reduced_plant),
the controller's design (``linearize``), the discrepancy replay and its named effects
(krang_model.effects) all evaluate ``WipDynamics.pitch_accelerations`` and step it with its one
integrator, ``step_pitch`` (the replay's large batches in place, through ``PitchBatch``, which
holds buffers and trigonometry and no physics); a new physical term is added here (its parameter
in ``krang_model.drivetrain.Drivetrain``, its line in ``pitch_accelerations``) and nowhere else.

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
step near a microsecond; arrays take the numpy path, in place in ``PitchBuffers``. Both paths run
the same lines.
"""

import copy
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


def _nonzero(x):
    return bool(np.any(x)) if isinstance(x, np.ndarray) else x != 0.0


class PitchBuffers:
    """The work arrays of ``WipDynamics``'s pitch equations and integrator for one shape: given
    as ``out``, every intermediate and result is written into them and nothing is allocated.
    ``sin_theta`` ... ``cos_tilt`` hold the exact sines and cosines of the last evaluation that
    computed them (``trig``: the four it used); ``a``-``d`` are scratch, ``m12`` the mass
    matrix's coupling, ``f1``/``f2`` the generalised forces and then the accelerations, ``inc``
    the last step's pitch increment, ``mask`` the caster contact."""

    __slots__ = (
        *('shape', 'trig', 'sin_theta', 'cos_theta', 'sin_tilt', 'cos_tilt'),
        *('a', 'b', 'c', 'd', 'm12', 'f1', 'f2', 'inc', 'mask'),
    )

    def __init__(self, shape):
        self.shape = tuple(shape)
        self.trig = None
        for name in self.__slots__[2:-1]:
            setattr(self, name, np.empty(self.shape))
        self.mask = np.empty(self.shape, bool)


class WipDynamics:
    """The nonlinear WIP with caster contact: the one implementation of the equations above.

    State: [phi, q_base, phi', q_base', psi, psi'] (phi: ground-referenced wheel angle, psi: yaw).
    Inputs: left and right wheel torques at the wheels (N m, after the gearbox). `body` and `drive`
    may hold arrays (poses, parameter sets); everything broadcasts against the state.

    ``pitch_accelerations`` states the pitch plane's equations once and ``step_pitch`` is the one
    integrator around them. Both take floats (a simulator step: math functions and Python
    operators, near a microsecond) or arrays, computed in place in ``PitchBuffers`` (``out``): the
    float form of an assignment and its in-place form (a numpy ufunc into ``out``) stand on one
    line, and the augmented assignments between them serve both (they rebind floats and update
    arrays in place)."""

    def __init__(self, body, drive):
        self.drive = d = drive
        self._j = d.reflected_rotor_inertia
        sin = np.sin if isinstance(d.floor_slope, _ndarray) else math.sin
        self._sin_slope = sin(d.floor_slope)
        self._yaw_arm = 0.5 * d.track_width / d.wheel_radius
        self._slope = d.floor_slope
        self._sloped = _nonzero(d.floor_slope)
        self._coulomb = _nonzero(d.coulomb_friction)
        self._coulomb2 = 2.0 * d.coulomb_friction
        self._ground = _nonzero(d.ground_viscous)
        self._caster_pitch = cp = d.caster_contact_pitch
        self._caster_max = float(cp.max()) if isinstance(cp, _ndarray) else cp
        self._set_body(body)

    def with_body(self, body):
        """The dynamics of another body on the same drive train (only the body's terms are
        computed again: the replay's moving poses)."""
        dyn = copy.copy(self)
        dyn._set_body(body)
        return dyn

    def _set_body(self, body):
        self.body = body
        d, j = self.drive, self._j
        self._m11 = (body.mass + d.wheel_mass) * d.wheel_radius**2 + d.wheel_inertia + j
        self._mrl = body.mass * d.wheel_radius * body.com_distance
        self._m22 = body.inertia_axle + j
        self._m11m22 = self._m11 * self._m22
        self._mgl = body.mass * d.gravity * body.com_distance
        self._grade = (body.mass + d.wheel_mass) * d.gravity * d.wheel_radius * self._sin_slope
        half = self._yaw_arm
        self._yaw_inertia = body.yaw_inertia + 2.0 * (d.wheel_inertia / 2 + j / 2) * half**2
        self._offset = body.com_offset
        self._terms = (
            *(self._offset, self._slope, self._coulomb2, self._grade, self._caster_pitch, j),
            *(self._m11, self._mrl, self._m22, self._m11m22, self._mgl),
            *(d.viscous_friction, d.ground_viscous, d.caster_stiffness, d.caster_damping),
        )
        self._numpy = any(isinstance(x, _ndarray) for x in self._terms)

    def _buffers(self, *xs):
        """New ``PitchBuffers`` of the shape the model's terms and `xs` broadcast to."""
        return PitchBuffers(np.broadcast_shapes(*map(np.shape, (*self._terms, *xs))))

    def caster_torque(self, q_base, dq_base, out=None):
        """The caster's unilateral penalty torque on the body (zero out of contact), at the pitch
        the caster geometry, the wheel radius and the floor slope give
        (``Drivetrain.caster_contact_pitch``). Floats, or into `out`'s arrays."""
        o = out
        if o is None and (self._numpy or type(q_base) is _ndarray or type(dq_base) is _ndarray):
            o = self._buffers(q_base, dq_base)
        return self._caster(q_base, dq_base, o)

    def _caster(self, q_base, dq_base, o):
        """``caster_torque`` for floats (`o` None) or into the ``PitchBuffers`` `o`."""
        floats = o is None
        k, c = self.drive.caster_stiffness, self.drive.caster_damping
        cp = self._caster_pitch
        pen = cp - q_base if floats else np.subtract(cp, q_base, o.a)
        touching = pen > 0.0 if floats else np.greater(pen, 0.0, o.mask)
        torque = pen * k if floats else np.multiply(pen, k, o.a)
        torque -= dq_base * c if floats else np.multiply(dq_base, c, o.b)
        torque = (torque if torque > 0.0 else 0.0) if floats else np.maximum(0.0, torque, o.a)
        torque *= touching
        return torque

    def pitch_accelerations(
        self, q_base, dphi, dq_base, tau, f_phi=None, f_qbase=None, trig=None, out=None
    ):
        """(phi'', q_base'') of the equations of the module docstring under the total wheel
        torque `tau` and optional extra generalised forces on the wheel and the pitch equations
        (N m): the one statement of the pitch physics.

        Floats, or arrays (new ones, of the broadcast shape); with `out` (``PitchBuffers`` of
        that shape) in place, the results then being ``out.f1`` and ``out.f2``. `trig`: (sin
        theta, cos theta, sin tilt, cos tilt) at q_base, theta = q_base + com_offset being the
        CoM angle from vertical and tilt = theta + floor slope; computed exactly if not given
        (with `out` into its arrays, ``out.trig``)."""
        d, o = self.drive, out
        if o is None and (
            self._numpy
            or type(q_base) is _ndarray
            or type(dphi) is _ndarray
            or type(dq_base) is _ndarray
            or type(tau) is _ndarray
        ):
            o = self._buffers(q_base, dphi, dq_base, tau, f_phi, f_qbase)
        floats = o is None
        if trig is None:  # exact, at the CoM angle theta and at the tilt theta + floor slope
            theta = q_base + self._offset if floats else np.add(q_base, self._offset, o.a)
            sin_theta = math.sin(theta) if floats else np.sin(theta, o.sin_theta)
            cos_theta = math.cos(theta) if floats else np.cos(theta, o.cos_theta)
            sin_tilt, cos_tilt = sin_theta, cos_theta
            if self._sloped:
                tilt = theta + self._slope if floats else np.add(theta, self._slope, o.a)
                sin_tilt = math.sin(tilt) if floats else np.sin(tilt, o.sin_tilt)
                cos_tilt = math.cos(tilt) if floats else np.cos(tilt, o.cos_tilt)
            if not floats:
                o.trig = (sin_theta, cos_theta, sin_tilt, cos_tilt)
        else:
            sin_theta, _, sin_tilt, cos_tilt = trig
        mrl = self._mrl
        # the wheels' friction against the body is a torque between the two, like the motors':
        # it enters the wheel and the pitch equations with opposite signs
        rel = dphi - dq_base if floats else np.subtract(dphi, dq_base, o.c)
        visc = d.viscous_friction
        internal = rel * visc if floats else np.multiply(rel, visc, o.d)
        if self._coulomb:
            coulomb = math.tanh(rel / 1e-2) if floats else np.tanh(np.divide(rel, 1e-2, o.a), o.a)
            coulomb *= self._coulomb2
            internal += coulomb
        # the mass matrix [[m11, m12], [m12, m22]]
        m12 = mrl * cos_tilt if floats else np.multiply(mrl, cos_tilt, o.m12)
        m12 -= self._j
        # wheel: centripetal, slope, motors, friction
        f1 = mrl * sin_tilt if floats else np.multiply(mrl, sin_tilt, o.f1)
        f1 *= dq_base
        f1 *= dq_base
        f1 -= self._grade
        f1 += tau
        f1 -= internal
        if self._ground:
            gv = d.ground_viscous
            f1 -= dphi * gv if floats else np.multiply(dphi, gv, o.a)
        # pitch: gravity, motors, friction, caster
        f2 = self._mgl * sin_theta if floats else np.multiply(self._mgl, sin_theta, o.f2)
        f2 -= tau
        f2 += internal
        if (q_base if floats else np.min(q_base)) < self._caster_max:  # on the caster
            f2 += self._caster(q_base, dq_base, o)
        if f_phi is not None:
            f1 += f_phi
            f2 += f_qbase
        # solved for the accelerations
        m11m22 = self._m11m22
        det = (
            m11m22 - m12 * m12 if floats else np.subtract(m11m22, np.multiply(m12, m12, o.a), o.a)
        )
        m12_f2 = m12 * f2 if floats else np.multiply(m12, f2, o.b)
        m12_f1 = m12 * f1 if floats else np.multiply(m12, f1, o.c)
        f1 *= self._m22
        f1 -= m12_f2
        f1 /= det
        f2 *= self._m11
        f2 -= m12_f1
        f2 /= det
        return f1, f2

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
        cos = np.cos if self._numpy or isinstance(qb, _ndarray) else math.cos
        theta = qb + self.body.com_offset
        kinetic = (
            0.5 * self._m11 * dphi**2
            + (self._mrl * cos(theta) - self._j) * dphi * dqb
            + 0.5 * self._m22 * dqb**2
            + 0.5 * self._yaw_inertia * dpsi**2
        )
        return kinetic + self._mgl * cos(theta)

    def step_pitch(
        self, phi, q_base, dphi, dq_base, tau, dt, f_phi=None, f_qbase=None, trig=None, out=None
    ):
        """One step of the pitch plane: (phi, q_base, phi', q_base') after `dt` under the total
        wheel torque `tau` (and optional extra generalised forces and sines and cosines, as
        ``pitch_accelerations``). The one integrator of the model: semi-implicit Euler
        (velocities first), symplectic, one force evaluation per step. Floats (a simulator step)
        or arrays (new ones, of the broadcast shape); with `out` (``PitchBuffers``) the four state
        arrays, of its shape, are updated in place (``PitchBatch``: the replay's batches)."""
        o, floats = out, out is None
        ddphi, ddqb = self.pitch_accelerations(q_base, dphi, dq_base, tau, f_phi, f_qbase, trig, o)
        if o is None and type(ddphi) is _ndarray:  # arrays: new ones, stepped in place
            phi, q_base, dphi, dq_base = (
                np.array(np.broadcast_to(x, ddphi.shape), float)
                for x in (phi, q_base, dphi, dq_base)
            )
        ddphi *= dt
        dphi += ddphi
        ddqb *= dt
        dq_base += ddqb
        phi += dphi * dt if floats else np.multiply(dphi, dt, o.a)
        inc = dq_base * dt if floats else np.multiply(dq_base, dt, o.inc)
        q_base += inc
        return phi, q_base, dphi, dq_base

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
    """In-place stepping of a large batch (the replay: parameter sets x windows, (P, S) arrays)
    with ``WipDynamics.step_pitch``: one set of ``PitchBuffers`` reused at every step, and the
    sines and cosines the equations take computed exactly every ``anchor`` steps and carried by
    rotation through each step's pitch increment in between (``_rotate``; in numpy's float64 path
    a sine or cosine costs about 50 multiplies). With ``anchor=1`` every step is ``step_pitch``
    bit for bit; otherwise they agree to rounding (1e-14). Buffers and trigonometry only: the
    physics is the dynamics'.

    ``set_dynamics(dyn)`` (a ``WipDynamics`` whose arrays broadcast to the shape) before the
    first step and whenever the body changes; ``step(phi, q_base, dphi, dq_base, tau, dt, f_phi,
    f_qbase)`` updates the four state arrays in place."""

    def __init__(self, shape, anchor: int = 16):
        self.shape = tuple(shape)
        self.anchor = max(1, int(anchor))
        self.buffers = PitchBuffers(self.shape)
        self._dyn = None
        self._offset = None
        self._trig = None
        self._steps = 0

    def set_dynamics(self, dyn):
        """The dynamics of the coming steps; the carried sines and cosines follow a change of the
        body's CoM offset (theta = q_base + com_offset)."""
        offset = np.array(np.broadcast_to(dyn.body.com_offset, self.shape), float)
        if self._trig is not None:
            self._rotate(offset - self._offset)
        self._offset = offset
        self._dyn = dyn

    def _rotate(self, delta):
        """Advance the sines and cosines by the angle increments `delta`: Taylor series to the
        6th order, off by less than 5e-15 for increments up to 0.03 rad (a pitch rate of 15 rad/s
        over a 2 ms step) and 1e-11 up to 0.09 rad, until the next exact anchor. Each element's
        result depends on its own increment alone, not on the batch it is in."""
        o = self.buffers
        d2 = np.multiply(delta, delta, out=o.d)
        sd = np.multiply(d2, 1.0 / 120.0, out=o.a)
        sd -= 1.0 / 6.0
        sd *= d2
        sd += 1.0
        sd *= delta  # sin(delta)
        cm = np.multiply(d2, -1.0 / 720.0, out=o.b)
        cm += 1.0 / 24.0
        cm *= d2
        cm -= 0.5
        cm *= d2  # cos(delta) - 1
        t = self._trig
        for s, c in ((t[0], t[1]),) if t[2] is t[0] else ((t[0], t[1]), (t[2], t[3])):
            ns = np.multiply(s, cm, out=o.c)
            ns += np.multiply(c, sd, out=o.m12)
            nc = np.multiply(c, cm, out=o.f1)
            nc -= np.multiply(s, sd, out=o.m12)
            s += ns
            c += nc

    def step(self, phi, q_base, dphi, dq_base, tau, dt, f_phi=None, f_qbase=None):
        exact = self._steps % self.anchor == 0
        trig = None if exact else self._trig
        o = self.buffers
        self._dyn.step_pitch(phi, q_base, dphi, dq_base, tau, dt, f_phi, f_qbase, trig, o)
        if exact:
            self._trig = o.trig
        self._steps += 1
        if self._steps % self.anchor:
            self._rotate(o.inc)


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
