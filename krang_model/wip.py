"""The robot as a wheeled inverted pendulum: reduction of a locked pose, dynamics, linearisation.

With the body joints locked the robot is one rigid body on two wheels. Its state is the ground-
referenced wheel angle phi (x = r phi, as the hardware's "x_wheel = encoders + IMU pitch"), the base
pitch q_base (IMU convention, FACTS §2) and the yaw psi. The body CoM angle from vertical is
theta = q_base + offset, where the offset is fixed by the pose and beta.

Equations (Lagrange; notes/identification.md §6 plus rotor inertia as in 18h linearize_wip.cpp,
plus a floor slope alpha and a caster contact):
  [(M+m_w) r^2 + I_w + J] phi'' + [M r l cos(theta+alpha) - J] theta''
      = M r l sin(theta+alpha) theta'^2 - (M+m_w) g r sin(alpha) + tau - b (phi'-theta') - b_g phi' - tau_c
  [M r l cos(theta+alpha) - J] phi'' + [I_axle + J] theta''
      = M g l sin(theta) - tau + b (phi'-theta') + tau_caster
with J = 2 gear^2 I_rotor the reflected rotor inertia of both drives, tau the sum of the wheel torques
and tau_c the wheels' Coulomb friction.
"""
import math
from dataclasses import dataclass

import numpy as np

from .com import base_regressor, base_to_frame0
from .kinematics import body_placements


@dataclass(frozen=True)
class WipBody:
    """A locked pose reduced to one rigid body on the axle (the wheels excluded)."""

    mass: float            # kg
    com_distance: float    # m, axle to body CoM
    com_offset: float      # rad, theta (CoM angle from vertical) = q_base + com_offset
    inertia_axle: float    # kg m^2 about the axle
    yaw_inertia: float     # kg m^2 about the vertical through the axle midpoint, wheels included
    com_offset_full: float  # rad, the same for the whole robot incl. wheels (what the learner balances)


def reduce_pose(robot, joints, beta):
    """WipBody of one locked pose (joints in pose order) under mass parameters beta."""
    beta = np.asarray(beta, dtype=float)
    joints = np.asarray(joints, dtype=float).reshape(1, -1)
    rot, trans = body_placements(robot, joints)
    rot, trans = rot[0], trans[0]
    body_ids = [i for i in range(robot.n_bodies) if i not in robot.wheel_body_ids]
    b4 = beta.reshape(-1, 4)
    moment_full = base_regressor(robot, joints)[0] @ beta
    mass = b4[body_ids, 0].sum()
    moment = np.zeros(3)
    inertia_axle = 0.0
    yaw_inertia = 0.0
    for i in body_ids:
        m = b4[i, 0]
        com = trans[i] + rot[i] @ (b4[i, 1:] / m if m != 0 else np.zeros(3))
        moment += m * com
        inertia_base = rot[i] @ robot.body_inertias[i] @ rot[i].T
        inertia_axle += inertia_base[0, 0] + m * (com[1] ** 2 + com[2] ** 2)
    com = moment / mass
    distance = math.hypot(com[1], com[2])
    offset = math.atan2(-com[2], com[1])
    # yaw inertia at balance (theta = 0): horizontal distances in frame 0
    r0 = base_to_frame0(-offset)[0]
    for i in body_ids:
        m = b4[i, 0]
        c0 = r0 @ (trans[i] + rot[i] @ (b4[i, 1:] / m if m != 0 else np.zeros(3)))
        yaw_inertia += (r0 @ rot[i] @ robot.body_inertias[i] @ rot[i].T @ r0.T)[2, 2] + m * (c0[0] ** 2 + c0[1] ** 2)
    for i in robot.wheel_body_ids:
        m = b4[i, 0]
        yaw_inertia += robot.body_inertias[i][1, 1] + m * trans[i][0] ** 2
    return WipBody(mass=float(mass), com_distance=distance, com_offset=offset,
                   inertia_axle=float(inertia_axle), yaw_inertia=float(yaw_inertia),
                   com_offset_full=math.atan2(-moment_full[2], moment_full[1]))


def linearize(body, drive):
    """Continuous A (4x4), B (4x1) about upright balance; state [x, x', theta, theta'], input the
    total wheel torque tau_w (N m) — the paper's (A(q), B(q)), B = [0, b_x, 0, b_theta]."""
    r, M, l = drive.wheel_radius, body.mass, body.com_distance
    j = drive.reflected_rotor_inertia
    m11 = (M + drive.wheel_mass) * r ** 2 + drive.wheel_inertia + j
    m12 = M * r * l - j
    m22 = body.inertia_axle + j
    delta = m11 * m22 - m12 ** 2
    b, bg, mgl = drive.viscous_friction, drive.ground_viscous, M * drive.gravity * l
    # generalized forces linear terms: F1 = tau - (b+bg) phi' + b theta', F2 = mgl theta - tau + b phi' - b theta'
    # [phi'', theta''] = inv([[m11, m12], [m12, m22]]) [F1, F2]
    inv = np.array([[m22, -m12], [-m12, m11]]) / delta
    d_theta = inv @ np.array([0.0, mgl])
    d_phidot = inv @ np.array([-(b + bg), b])
    d_thetadot = inv @ np.array([b, -b])
    d_tau = inv @ np.array([1.0, -1.0])
    a = np.zeros((4, 4))
    a[0, 1] = 1.0
    a[2, 3] = 1.0
    a[1] = [0.0, d_phidot[0], r * d_theta[0], r * d_thetadot[0]]
    a[3] = [0.0, d_phidot[1] / r, d_theta[1], d_thetadot[1]]
    bmat = np.array([[0.0], [r * d_tau[0]], [0.0], [d_tau[1]]])
    return a, bmat


class WipDynamics:
    """Nonlinear WIP with caster contact; scalar float math so one step costs microseconds.

    State: [phi, q_base, phi', q_base', psi, psi'] (phi = ground-referenced wheel angle, psi = yaw).
    Inputs: left and right wheel torques at the wheels (N m, after the gearbox).
    """

    def __init__(self, body, drive):
        self.body = body
        self.drive = drive
        d = drive
        self._j = d.reflected_rotor_inertia
        self._m11 = (body.mass + d.wheel_mass) * d.wheel_radius ** 2 + d.wheel_inertia + self._j
        self._mrl = body.mass * d.wheel_radius * body.com_distance
        self._m22 = body.inertia_axle + self._j
        self._mgl = body.mass * d.gravity * body.com_distance
        self._grade = (body.mass + d.wheel_mass) * d.gravity * d.wheel_radius * math.sin(d.floor_slope)
        half = 0.5 * d.track_width / d.wheel_radius
        self._yaw_inertia = body.yaw_inertia + 2.0 * (d.wheel_inertia / 2 + self._j / 2) * half ** 2
        self._yaw_arm = 0.5 * d.track_width / d.wheel_radius

    def caster_torque(self, q_base, dq_base):
        d = self.drive
        pen = d.caster_pitch - q_base
        if pen <= 0.0:
            return 0.0
        return max(0.0, d.caster_stiffness * pen - d.caster_damping * dq_base)

    def accelerations(self, state, tau_left, tau_right):
        """(phi'', q_base'', psi'') at `state` under the given wheel torques."""
        phi, qb, dphi, dqb, psi, dpsi = state
        d = self.drive
        theta = qb + self.body.com_offset
        c = math.cos(theta + d.floor_slope)
        s_slope = math.sin(theta + d.floor_slope)
        tau = tau_left + tau_right
        rel = dphi - dqb
        friction = d.viscous_friction * rel + d.ground_viscous * dphi
        if d.coulomb_friction:
            friction += 2.0 * d.coulomb_friction * math.tanh(rel / 1e-2)
        m12 = self._mrl * c - self._j
        f1 = self._mrl * s_slope * dqb * dqb - self._grade + tau - friction
        f2 = self._mgl * math.sin(theta) - tau + d.viscous_friction * rel + self.caster_torque(qb, dqb)
        delta = self._m11 * self._m22 - m12 * m12
        ddphi = (self._m22 * f1 - m12 * f2) / delta
        ddqb = (self._m11 * f2 - m12 * f1) / delta
        ddpsi = ((tau_right - tau_left) * self._yaw_arm - d.yaw_friction * dpsi) / self._yaw_inertia
        return ddphi, ddqb, ddpsi

    def energy(self, state):
        """Kinetic + potential energy (J), for conservation checks (slope and caster excluded)."""
        phi, qb, dphi, dqb, psi, dpsi = state
        theta = qb + self.body.com_offset
        kinetic = 0.5 * self._m11 * dphi ** 2 + (self._mrl * math.cos(theta) - self._j) * dphi * dqb \
            + 0.5 * self._m22 * dqb ** 2 + 0.5 * self._yaw_inertia * dpsi ** 2
        return kinetic + self._mgl * math.cos(theta)

    def step(self, state, tau_left, tau_right, dt):
        """Semi-implicit Euler (velocities first): symplectic, one force evaluation per step."""
        ddphi, ddqb, ddpsi = self.accelerations(state, tau_left, tau_right)
        dphi = state[2] + dt * ddphi
        dqb = state[3] + dt * ddqb
        dpsi = state[5] + dt * ddpsi
        return [state[0] + dt * dphi, state[1] + dt * dqb, dphi, dqb, state[4] + dt * dpsi, dpsi]

    def step_rk4(self, state, tau_left, tau_right, dt):
        """Classical RK4 (four force evaluations) for accuracy checks."""
        def f(s):
            a = self.accelerations(s, tau_left, tau_right)
            return [s[2], s[3], a[0], a[1], s[5], a[2]]
        k1 = f(state)
        k2 = f([x + 0.5 * dt * k for x, k in zip(state, k1)])
        k3 = f([x + 0.5 * dt * k for x, k in zip(state, k2)])
        k4 = f([x + dt * k for x, k in zip(state, k3)])
        return [x + dt / 6.0 * (a + 2 * b + 2 * c + d) for x, a, b, c, d in zip(state, k1, k2, k3, k4)]

    def wheel_torques_from_currents(self, current_left, current_right):
        """Motor currents (A, clamped at the limit) to wheel torques (N m)."""
        d = self.drive
        k = d.torque_constant * d.gear_ratio
        lim = d.current_limit
        return k * min(max(current_left, -lim), lim), k * min(max(current_right, -lim), lim)
