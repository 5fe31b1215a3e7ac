"""The robot as a wheeled inverted pendulum: reduction of locked poses, dynamics, linearisation.

This module is the one statement of the WIP physics: ``pitch_equations`` (the accelerations),
``body_terms`` (their coefficients) and ``semi_implicit_euler`` (the one integrator). The reduced
plant (krang_sim.reduced_plant), the controller's design (``linearize``) and the named effects
(krang_model.effects) evaluate them through ``WipDynamics``; the discrepancy replay runs the same
functions compiled over its large batches (``krang_model.wip_batch``). A new physical term is
added here (its parameter in ``krang_model.drivetrain.Drivetrain``, its line in
``pitch_equations``) and nowhere else.

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
and of states steps in one call. The equations are written with operators and ``smooth_sign``
alone (no branches), so floats, arrays and the compiled batch run the same lines.
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
        (kg m^2) more inertia about the axle (``adjusted_body``): the named effects com_height
        and body_inertia."""
        dist, inertia = adjusted_body(
            self.mass, self.com_distance, self.inertia_axle, com_shift, inertia_add
        )
        return replace(self, com_distance=dist, inertia_axle=inertia)


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


def smooth_sign(x):
    """tanh(x), the Coulomb friction's smoothing of its sign (compiled, ``wip_batch`` runs a tanh
    that SIMD lanes can take, within a few ulp of this one)."""
    return np.tanh(x) if isinstance(x, _ndarray) else math.tanh(x)


def body_terms(
    mass, com_distance, inertia_axle, wheel_mass, wheel_radius, wheel_inertia, rotor, gravity,
    sin_slope,
):  # fmt: skip
    """The pitch equations' coefficients of a body on a drive train: (m11, M r l, m22, m11 m22,
    M g l, the slope's grade torque), rotor = J the reflected rotor inertia. Floats, arrays or
    compiled, like ``pitch_equations``."""
    m11 = (mass + wheel_mass) * (wheel_radius * wheel_radius) + wheel_inertia + rotor
    mrl = mass * wheel_radius * com_distance
    m22 = inertia_axle + rotor
    mgl = mass * gravity * com_distance
    grade = (mass + wheel_mass) * gravity * wheel_radius * sin_slope
    return m11, mrl, m22, m11 * m22, mgl, grade


def adjusted_body(mass, com_distance, inertia_axle, com_shift, inertia_add):
    """(com distance, inertia about the axle) with the CoM moved `com_shift` (m) farther from the
    axle along its direction (a point-mass shift: M l -> M (l + dl), I += M ((l + dl)^2 - l^2))
    and `inertia_add` (kg m^2) more inertia: the named effects com_height and body_inertia."""
    inertia = inertia_axle + inertia_add + mass * com_shift * (2 * com_distance + com_shift)
    return com_distance + com_shift, inertia


def caster_torque(q_base, dq_base, caster_pitch, stiffness, damping):
    """The caster's unilateral penalty torque on the body (zero out of contact, never pulling)."""
    pen = caster_pitch - q_base
    torque = pen * stiffness - dq_base * damping
    return torque * (pen > 0.0) * (torque > 0.0)


def pitch_equations(
    q_base, dphi, dq_base, tau, f_phi, f_qbase, sin_theta, sin_tilt, cos_tilt,
    m11, mrl, m22, m11m22, mgl, grade, rotor, viscous, coulomb, ground,
    caster_pitch, caster_stiffness, caster_damping,
):  # fmt: skip
    """(phi'', q_base'') of the module docstring's equations: the one statement of the pitch
    physics. Operators and ``smooth_sign`` only, no branches, so the same lines run on floats
    (a simulator step), on numpy arrays (a batch) and compiled (``krang_model.wip_batch``).
    theta is the CoM angle from vertical, tilt = theta + the floor slope; coulomb is each wheel's
    Coulomb friction (N m); f_phi and f_qbase extra generalised forces (N m)."""
    # the wheels' friction against the body is a torque between the two, like the motors': it
    # enters the wheel and the pitch equations with opposite signs
    rel = dphi - dq_base
    internal = rel * viscous + 2.0 * coulomb * smooth_sign(rel / 1e-2)
    # the mass matrix [[m11, m12], [m12, m22]]
    m12 = mrl * cos_tilt - rotor
    # wheel: centripetal, slope, motors, friction; pitch: gravity, motors, friction, caster
    f1 = mrl * sin_tilt * dq_base * dq_base - grade + tau - internal - dphi * ground + f_phi
    f2 = mgl * sin_theta - tau + internal + f_qbase
    f2 = f2 + caster_torque(q_base, dq_base, caster_pitch, caster_stiffness, caster_damping)
    det = m11m22 - m12 * m12
    return (f1 * m22 - m12 * f2) / det, (f2 * m11 - m12 * f1) / det


def semi_implicit_euler(phi, q_base, dphi, dq_base, ddphi, ddqb, dt):
    """The one integrator of the model: velocities first, then positions with the new velocities
    (symplectic, one force evaluation per step)."""
    dphi = dphi + ddphi * dt
    dq_base = dq_base + ddqb * dt
    return phi + dphi * dt, q_base + dq_base * dt, dphi, dq_base


class WipDynamics:
    """The nonlinear WIP with caster contact, around the one statement of its equations
    (``pitch_equations``) and its one integrator (``semi_implicit_euler``).

    State: [phi, q_base, phi', q_base', psi, psi'] (phi: ground-referenced wheel angle, psi: yaw).
    Inputs: left and right wheel torques at the wheels (N m, after the gearbox). `body` and `drive`
    may hold arrays (poses, parameter sets); everything broadcasts against the state. Floats take
    ``math`` (a simulator step, a few microseconds), arrays numpy; the replay's large batches run
    the same functions compiled (``krang_model.wip_batch``)."""

    def __init__(self, body, drive):
        self.drive = d = drive
        self._j = d.reflected_rotor_inertia
        sin = np.sin if isinstance(d.floor_slope, _ndarray) else math.sin
        self._sin_slope = sin(d.floor_slope)
        self._yaw_arm = 0.5 * d.track_width / d.wheel_radius
        self._slope = d.floor_slope
        self._sloped = bool(np.any(d.floor_slope))
        self._set_body(body)

    def with_body(self, body):
        """The dynamics of another body on the same drive train."""
        dyn = copy.copy(self)
        dyn._set_body(body)
        return dyn

    def _set_body(self, body):
        self.body = body
        d, j = self.drive, self._j
        self._m11, self._mrl, m22, m11m22, self._mgl, grade = terms = body_terms(
            body.mass,
            body.com_distance,
            body.inertia_axle,
            d.wheel_mass,
            d.wheel_radius,
            d.wheel_inertia,
            j,
            d.gravity,
            self._sin_slope,
        )
        self._coefficients = (*terms, j, d.viscous_friction, d.coulomb_friction, d.ground_viscous)
        self._caster = (d.caster_contact_pitch, d.caster_stiffness, d.caster_damping)
        self._yaw_inertia = (
            body.yaw_inertia + 2.0 * (d.wheel_inertia / 2 + j / 2) * self._yaw_arm**2
        )
        self._offset = body.com_offset
        self._numpy = any(isinstance(x, _ndarray) for x in (*self._coefficients, self._offset))

    def caster_torque(self, q_base, dq_base):
        """The caster's torque on the body (zero out of contact), at the pitch the caster
        geometry, the wheel radius and the floor slope give
        (``Drivetrain.caster_contact_pitch``)."""
        return caster_torque(q_base, dq_base, *self._caster)

    def _sin_cos(self, q_base):
        """(sin theta, sin tilt, cos tilt) at q_base."""
        arrays = self._numpy or isinstance(q_base, _ndarray)
        sin, cos = (np.sin, np.cos) if arrays else (math.sin, math.cos)
        theta = q_base + self._offset
        sin_theta = sin(theta)
        if not self._sloped:  # tilt = theta: the same numbers, two calls fewer
            return sin_theta, sin_theta, cos(theta)
        tilt = theta + self._slope
        return sin_theta, sin(tilt), cos(tilt)

    def pitch_accelerations(self, q_base, dphi, dq_base, tau, f_phi=0.0, f_qbase=0.0):
        """(phi'', q_base'') under the total wheel torque `tau` and optional extra generalised
        forces on the wheel and the pitch equations (N m): ``pitch_equations`` at this body and
        drive train."""
        trig = self._sin_cos(q_base)
        return pitch_equations(
            q_base, dphi, dq_base, tau, f_phi, f_qbase, *trig, *self._coefficients, *self._caster
        )

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
        m22 = self._coefficients[2]
        kinetic = (
            0.5 * self._m11 * dphi**2
            + (self._mrl * cos(theta) - self._j) * dphi * dqb
            + 0.5 * m22 * dqb**2
            + 0.5 * self._yaw_inertia * dpsi**2
        )
        return kinetic + self._mgl * cos(theta)

    def step_pitch(self, phi, q_base, dphi, dq_base, tau, dt, f_phi=0.0, f_qbase=0.0):
        """One step of the pitch plane: (phi, q_base, phi', q_base') after `dt` under the total
        wheel torque `tau` (and optional extra generalised forces): ``semi_implicit_euler`` of
        ``pitch_accelerations``. Floats, or new arrays of the broadcast shape."""
        ddphi, ddqb = self.pitch_accelerations(q_base, dphi, dq_base, tau, f_phi, f_qbase)
        return semi_implicit_euler(phi, q_base, dphi, dq_base, ddphi, ddqb, dt)

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
