"""The reduced plant: Krang as the wheeled inverted pendulum of ``krang_model.wip`` with a hidden
true beta, its body joints moving as the Schunk modules do. Registered as ``'reduced'``.

The body joints move rate-limited to each module's speed. While they move, the locked-pose
reduction is recomputed every ``reduce_period`` (quasi-static arms: at <= 0.44 rad/s the joints'
own momentum is negligible against the 150 kg body).

The true robot is ``ModelTerms`` of ``krang_model.effects`` (default: nominal): its drive train
(torque constant, friction, floor slope, wheel radius ... the fields ``WipDynamics`` integrates),
payloads (point masses added to the true beta), the body adjustments (``com_shift``,
``inertia_add``), extra generalised forces, and the command delay (``krang_sim.sensors.
CommandDelay``). The sensor-side terms are the sensor model's.

Speed. The hot path of the offline campaigns (joints at rest and reduced where they are, no command
delay, no extra force) calls ``WipDynamics.step`` directly with the torques held over ``step(n)``,
and ``wheel_pitch()`` gives the controller's part of the motion without building a ``Motion``.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from krang_model.drivetrain import drivetrain
from krang_model.effects import ModelTerms
from krang_model.wip import WipDynamics, point_mass_beta, reduce_pose

from .plant import Motion, Plant, Truth, register_plant
from .sensors import CommandDelay


def true_beta_of(robot, beta, terms):
    """The true robot's beta: `beta` with the payloads of `terms` added."""
    for link, point, kg in terms.payloads:
        beta = point_mass_beta(robot, beta, link, point, kg)
    return np.array(beta, dtype=float)


@register_plant
class ReducedPlant(Plant):
    """The reduced WIP plant (see the module docstring)."""

    name = 'reduced'
    #: kept up to date by command_joints and the steps (read at every sample: no property)
    joints_moving: bool = False

    def __init__(
        self,
        robot,
        true_beta,
        joints,
        *,
        q_base=None,
        terms: ModelTerms | None = None,
        dt: float = 1e-3,
        reduce_period: float = 0.02,
    ):
        self.robot = robot
        self.terms = terms = terms if terms is not None else ModelTerms.nominal(drivetrain(robot))
        self.dt = float(dt)
        self.reduce_period = float(reduce_period)
        self.drive = drive = terms.drive
        self.true_beta = true_beta_of(robot, true_beta, terms)
        self._adjust = (float(terms.com_shift), float(terms.inertia_add))
        self._extra = list(terms.extra_forces)
        self.t = 0.0
        self.joints = np.array(joints, dtype=float)
        self.joint_targets = self.joints.copy()
        self._reduced_at = self.joints.copy()
        self._since_reduce = 0.0
        self._target_changed = False
        self._still = False  # at rest at the pose last reduced (_move_joints skips its work)
        self._move_steps = 0
        self.joints_moving = False
        self.dynamics = self._dynamics()
        pitch = drive.caster_pitch if q_base is None else q_base
        self.state = [0.0, pitch, 0.0, 0.0, 0.0, 0.0]
        self._accel = (0.0, 0.0, 0.0)
        self._current_cmd = (0.0, 0.0)
        self._delay = CommandDelay(terms.actuation_delay, self.dt)
        self.applied_current = (0.0, 0.0)
        self._kt = drive.torque_constant * drive.gear_ratio
        self._half = 0.5 * drive.track_width / drive.wheel_radius

    def _dynamics(self):
        body = reduce_pose(self.robot, self.joints, self.true_beta)
        if self._adjust != (0.0, 0.0):
            body = body.adjusted(com_shift=self._adjust[0], inertia_add=self._adjust[1])
        return WipDynamics(body, self.drive)

    def set_true_beta(self, beta):
        """A new hidden mass model from now on (a payload that grows, say); payloads of the
        terms are added to it."""
        self.true_beta = true_beta_of(self.robot, beta, self.terms)
        self.dynamics = self._dynamics()

    # --- commands -------------------------------------------------------------------------------
    def command_currents(self, left_a, right_a):
        self._current_cmd = (float(left_a), float(right_a))

    def command_joints(self, targets):
        targets = np.clip(np.asarray(targets, dtype=float), self.robot.lower, self.robot.upper)
        self._target_changed = self._target_changed or not np.array_equal(
            targets, self.joint_targets
        )
        self.joint_targets = targets
        self.joints_moving = bool(np.any(np.abs(targets - self.joints) > 1e-9))

    def push(self, pitch_rate):
        self.state[3] += float(pitch_rate)

    # --- physics --------------------------------------------------------------------------------
    def step(self, n=1):
        if not self._still or self._target_changed or self._delay.active or self._extra:
            for _ in range(n):
                self._step_one()
            return
        # hot path: the joints at rest where the pose was last reduced (what _move_joints would
        # confirm), no delay, no extra force: the torques hold over the n steps
        dt = self.dt
        lim = self.drive.current_limit
        cl, cr = self._current_cmd
        il = lim if cl > lim else (-lim if cl < -lim else cl)
        ir = lim if cr > lim else (-lim if cr < -lim else cr)
        self.applied_current = (il, ir)
        tl, tr = self._kt * il, self._kt * ir
        dyn = self.dynamics
        state = self.state
        prev = state
        for _ in range(n):
            prev = state
            state = dyn.step(prev, tl, tr, dt)
            self.t += dt
        self.state = state
        self._accel = (
            (state[2] - prev[2]) / dt,
            (state[3] - prev[3]) / dt,
            (state[5] - prev[5]) / dt,
        )

    def _step_one(self):
        dt = self.dt
        lim = self.drive.current_limit
        applied = self._delay.push(self._current_cmd)
        il = min(max(applied[0], -lim), lim)
        ir = min(max(applied[1], -lim), lim)
        self.applied_current = (il, ir)
        self._move_joints(dt)
        prev = self.state
        tl, tr = self._kt * il, self._kt * ir
        if self._extra:
            self.state = self._step_extra(prev, tl, tr, dt)
        else:
            self.state = self.dynamics.step(prev, tl, tr, dt)
        self._accel = (
            (self.state[2] - prev[2]) / dt,
            (self.state[3] - prev[3]) / dt,
            (self.state[5] - prev[5]) / dt,
        )
        self.t += dt
        if self.joints_moving and not np.any(np.abs(self.joint_targets - self.joints) > 1e-9):
            self.joints_moving = False

    def _step_extra(self, state, tl, tr, dt):
        """A step with the terms' extra generalised forces, evaluated at the state."""
        dyn = self.dynamics
        phi, qb, dphi, dqb, psi, dpsi = state
        s = SimpleNamespace(
            t=self.t,
            phi=phi,
            q_base=qb,
            dphi=dphi,
            dq_base=dqb,
            theta=qb + dyn.body.com_offset,
            tau=tl + tr,
        )
        f_phi = f_qbase = 0.0
        for force in self._extra:
            a, b = force(s)
            f_phi, f_qbase = f_phi + float(a), f_qbase + float(b)
        phi, qb, dphi, dqb = dyn.step_pitch(phi, qb, dphi, dqb, tl + tr, dt, f_phi, f_qbase)
        dpsi = dpsi + dt * dyn.yaw_acceleration(dpsi, tl, tr)
        return [phi, qb, dphi, dqb, psi + dt * dpsi, dpsi]

    def _move_joints(self, dt):
        """Rate-limited joints; the pose is re-reduced every `reduce_period` while they move and
        when they arrive. Arrival counts once the target holds still: under a ramping target (the
        PowerCube emulators move the target a little every step) the joints reach it at every step,
        and re-reducing each time cost ~500 reductions of 5 ms per simulated second, which held
        sim_krang at a fraction of real time, with 5 ms stalls, during every pose move."""
        if self._still and not self._target_changed:
            return  # at rest, reduced at this pose, and no new target: nothing below would change
        self._still = False
        changed, self._target_changed = self._target_changed, False
        error = self.joint_targets - self.joints
        if np.any(np.abs(error) > 1e-9):
            max_step = self.robot.velocity_limit * dt
            self.joints += np.clip(error, -max_step, max_step)
            self._since_reduce += dt
            self._move_steps += 1
            arrived = not np.any(np.abs(self.joint_targets - self.joints) > 1e-9)
            if arrived and not changed:
                self._move_steps = 0  # arrived at a target that holds still
            elif self._since_reduce < self.reduce_period and not (
                arrived and self._move_steps == 1
            ):
                return
        else:
            self._move_steps = 0
            if np.array_equal(self.joints, self._reduced_at):
                self._still = True
                return  # still, and reduced at this pose
        self._since_reduce = 0.0
        self._reduced_at = self.joints.copy()
        self.dynamics = self._dynamics()

    # --- what the sensors see -------------------------------------------------------------------
    @property
    def q_base(self):
        return self.state[1]

    @property
    def axle_acceleration(self):
        """Forward acceleration of the axle along the floor (m/s^2) over the last step."""
        return self.drive.wheel_radius * self._accel[0]

    def wheel_pitch(self):
        ph, qb, dph, dqb, psi, dpsi = self.state
        half = self._half
        rel = ph - qb
        return (
            self.t,
            qb,
            dqb,
            rel - half * psi,
            rel + half * psi,
            dph - dqb - half * dpsi,
            dph - dqb + half * dpsi,
        )

    def motion(self) -> Motion:
        phi, qb, dphi, dqb, psi, dpsi = self.state
        d = self.drive
        # Specific force at the axle (the IMU sits on the base): the axle accelerates along the
        # floor, gravity points down. Base y = (sin qb, cos qb) and base z = (-cos qb, sin qb) in
        # frame 0 (x, z).
        a_fwd = d.wheel_radius * self._accel[0]
        slope = d.floor_slope
        ax, az = a_fwd * math.cos(slope), a_fwd * math.sin(slope) + d.gravity
        c, s = math.cos(qb), math.sin(qb)
        wl, wr, dwl, dwr = self.wheel_pitch()[3:]
        return Motion(
            t=self.t,
            q_base=qb,
            dq_base=dqb,
            # pitch about -x (RotX(-q_base)), yaw about frame-0 z
            gyro=(-dqb, dpsi * c, dpsi * s),
            specific_force=(0.0, s * ax + c * az, -c * ax + s * az),
            wheel_left=wl,
            wheel_right=wr,
            wheel_left_rate=dwl,
            wheel_right_rate=dwr,
            joints=self.joints.copy(),
            applied_current=self.applied_current,
        )

    # --- truth ----------------------------------------------------------------------------------
    def balance_pitch(self):
        """The q_base at which the true robot (pose as it is now) balances."""
        return -self.dynamics.body.com_offset_full

    def truth(self) -> Truth:
        st = self.state
        # positional (t, x_m, q_base, dq_base, yaw, balance_pitch, state): the loop logs at 30 Hz
        return Truth(
            self.t,
            self.drive.wheel_radius * st[0],
            st[1],
            st[3],
            st[4],
            -self.dynamics.body.com_offset_full,
            tuple(st),
        )
