"""The simulated Krang: WIP physics with a hidden true beta, position-controlled body joints, and
the sensors and actuators as the hardware has them. No CAN and no ROS here (see devices.py,
node.py).

The body joints move as the Schunk modules do, rate-limited to each module's speed. While they
move, the locked-pose reduction is recomputed every `reduce_period` (quasi-static arms: at <= 0.44
rad/s the joints' own momentum is negligible against the 150 kg body).

`SimEffects` are physical effects the nominal model leaves out. The simulator can switch each one
on with a value, and `krang discrepancy` has to name them from data. The physical ones are values
of the drive train (``SimEffects.drive``): the equations are krang_model.wip's, nothing here
restates them.
"""

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from krang_model.drivetrain import drivetrain
from krang_model.wip import WipDynamics, point_mass_beta, reduce_pose


@dataclass
class SimEffects:
    """Deviations of the true robot from the nominal model (all zero = nominal). Units in names."""

    imu_pitch_bias_rad: float = 0.0  # the IMU reads q_base + bias
    floor_slope_rad: float = 0.0  # ground rises along the heading
    wheel_radius_m: float = 0.0  # effective rolling radius; 0 = the URDF's
    payload_kg: float = 0.0  # an unmodelled mass ...
    payload_body: str = 'lGripper'  # ... rigidly on this body ...
    payload_com_m: tuple = (0.0, 0.0, 0.10)  # ... at this point of its frame
    wheel_viscous_Nm_s: float = 0.0  # extra wheel-to-body viscous friction (both wheels)
    wheel_coulomb_Nm: float = 0.0  # extra Coulomb friction per wheel
    torque_constant_scale: float = 1.0  # true Kt / nominal Kt
    actuation_delay_s: float = 0.0  # transport delay of the wheel current commands
    encoder_offset_rad: float = 0.0  # the waist encoder reads q + offset
    encoder_offset_joint: str = 'JWaist'
    drive_extra: dict = field(default_factory=dict)  # amounts added to any Drivetrain field

    def drive(self, robot):
        """The true robot's Drivetrain: the nominal one with these effects."""
        nominal = drivetrain(robot)
        extra = dict(self.drive_extra)
        for name, amount in (
            ('floor_slope', self.floor_slope_rad),
            ('viscous_friction', self.wheel_viscous_Nm_s),
            ('coulomb_friction', self.wheel_coulomb_Nm),
        ):
            extra[name] = extra.get(name, 0.0) + amount
        values = {k: getattr(nominal, k) + v for k, v in extra.items()}
        if self.wheel_radius_m:
            values['wheel_radius'] = self.wheel_radius_m
        values['torque_constant'] = nominal.torque_constant * self.torque_constant_scale
        return replace(nominal, **values)


@dataclass
class SensorNoise:
    """Noise and resolution of the hardware sensors (krang_model/README.md, Sensors)."""

    imu_pitch_std_rad: float = math.radians(0.1)
    gyro_std_rad_s: float = 0.002
    gyro_lsb_rad_s: float = math.radians(0.008)  # DMU: 0.008 deg/s per LSB
    accel_lsb_m_s2: float = 0.0003 * 9.80665  # DMU: 0.0003 g per LSB
    accel_std_m_s2: float = 0.02
    # motor encoder through the gearbox; the device map (config/can_devices.yaml, wheels) is the
    # one source the bridge reads, and test_sim_physics checks this default against it
    encoder_counts_per_rad: float = 4000 * 15 / (2 * math.pi)
    joint_std_rad: float = 1e-4


@dataclass
class SimConfig:
    dt: float = 1e-3  # physics step (s)
    reduce_period: float = 0.02  # re-reduction of a moving pose (s)
    effects: SimEffects = field(default_factory=SimEffects)
    noise: SensorNoise = field(default_factory=SensorNoise)
    seed: int = 0


@dataclass
class Sensors:
    """One sample of everything the robot's devices report."""

    t: float
    q_base: float  # IMU pitch as the bridge's filter reports it (here: truth + bias + noise)
    pitch_rate: float  # d q_base / dt (rad/s)
    gyro: tuple  # angular velocity in the base frame (rad/s), DMU-quantised
    specific_force: tuple  # specific force in the base frame (m/s^2), DMU-quantised
    wheel_left: float  # encoder angle relative to the body (rad, wheel side, quantised)
    wheel_right: float
    wheel_left_rate: float
    wheel_right_rate: float
    joints: np.ndarray  # body joint encoders (rad), pose order
    wheel_current_left: float  # current the drives apply (A)
    wheel_current_right: float


def payload_beta(robot, beta, effects):
    """beta of the true robot including an unmodelled payload."""
    return point_mass_beta(
        robot, beta, effects.payload_body, effects.payload_com_m, effects.payload_kg
    )


class KrangSim:
    """The true robot. Call `command_currents` / `command_joints`, then `step()`; read
    `sensors()`."""

    def __init__(self, robot, true_beta, joints, q_base=None, config=None):
        self.robot = robot
        self.config = config or SimConfig()
        fx = self.config.effects
        self.true_beta = payload_beta(robot, true_beta, fx)
        self.drive = fx.drive(robot)
        self.rng = np.random.default_rng(self.config.seed)
        self.t = 0.0
        self.joints = np.array(joints, dtype=float)
        self.joint_targets = self.joints.copy()
        self._reduced_at = self.joints.copy()
        self._since_reduce = 0.0
        self._target_changed = False
        self._still = False  # at rest at the pose last reduced (_move_joints skips its work)
        self._move_steps = 0
        self.dynamics = WipDynamics(reduce_pose(robot, self.joints, self.true_beta), self.drive)
        pitch = self.drive.caster_pitch if q_base is None else q_base
        self.state = [0.0, pitch, 0.0, 0.0, 0.0, 0.0]
        self._accel = (0.0, 0.0, 0.0)
        self._current_cmd = (0.0, 0.0)
        self._delay = deque()
        self.applied_current = (0.0, 0.0)
        self._enc_offset = np.zeros(len(self.joints))
        if fx.encoder_offset_rad:
            self._enc_offset[robot.pose_joints.index(fx.encoder_offset_joint)] = (
                fx.encoder_offset_rad
            )

    # --- commands -------------------------------------------------------------------------------
    def command_currents(self, left_a, right_a):
        """Motor currents the drives are asked for (A); the drives clamp them at the current
        limit."""
        self._current_cmd = (float(left_a), float(right_a))

    def command_joints(self, targets):
        """Body joint position targets (rad, pose order), clamped to the URDF limits."""
        targets = np.clip(np.asarray(targets, dtype=float), self.robot.lower, self.robot.upper)
        self._target_changed = self._target_changed or not np.array_equal(
            targets, self.joint_targets
        )
        self.joint_targets = targets

    # --- physics --------------------------------------------------------------------------------
    def step(self, n=1):
        dt = self.config.dt
        delay_steps = int(round(self.config.effects.actuation_delay_s / dt))
        kt = self.drive.torque_constant * self.drive.gear_ratio
        lim = self.drive.current_limit
        for _ in range(n):
            self._delay.append(self._current_cmd)
            applied = self._delay.popleft() if len(self._delay) > delay_steps else (0.0, 0.0)
            il = min(max(applied[0], -lim), lim)
            ir = min(max(applied[1], -lim), lim)
            self.applied_current = (il, ir)
            self._move_joints(dt)
            prev = self.state
            self.state = self.dynamics.step(prev, kt * il, kt * ir, dt)
            self._accel = (
                (self.state[2] - prev[2]) / dt,
                (self.state[3] - prev[3]) / dt,
                (self.state[5] - prev[5]) / dt,
            )
            self.t += dt

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
            elif self._since_reduce < self.config.reduce_period and not (
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
        self.dynamics = WipDynamics(
            reduce_pose(self.robot, self.joints, self.true_beta), self.drive
        )

    @property
    def joints_moving(self):
        return bool(np.any(np.abs(self.joint_targets - self.joints) > 1e-9))

    # --- truth ----------------------------------------------------------------------------------
    @property
    def q_base(self):
        return self.state[1]

    @property
    def x(self):
        """Distance travelled along the floor (m)."""
        return self.drive.wheel_radius * self.state[0]

    @property
    def axle_acceleration(self):
        """Forward acceleration of the axle along the floor (m/s^2) over the last step."""
        return self.drive.wheel_radius * self._accel[0]

    def balance_pitch(self):
        """The q_base at which the true robot (pose as it is now) balances."""
        return -self.dynamics.body.com_offset_full

    # --- sensors --------------------------------------------------------------------------------
    def sensors(self):
        cfg = self.config
        noise, fx, rng = cfg.noise, cfg.effects, self.rng
        phi, qb, dphi, dqb, psi, dpsi = self.state
        ddphi, _, _ = self._accel
        r = self.drive.wheel_radius
        g = self.drive.gravity
        # Specific force at the axle (the IMU sits on the base): the axle accelerates along the
        # floor, gravity points down. Base y = (sin qb, cos qb) and base z = (-cos qb, sin qb) in
        # frame 0 (x, z). An IMU bias is a pitch misalignment of the sensor, so it enters as qb +
        # bias.
        a_fwd = r * ddphi
        slope = fx.floor_slope_rad
        ax, az = a_fwd * math.cos(slope), a_fwd * math.sin(slope) + g
        seen = qb + fx.imu_pitch_bias_rad
        c, s = math.cos(seen), math.sin(seen)
        f_y, f_z = s * ax + c * az, -c * ax + s * az
        # angular velocity in the base frame: pitch about -x (RotX(-q_base)), yaw about frame-0 z
        gyro = (-dqb, dpsi * c, dpsi * s)

        def q(v, lsb):
            return round(v / lsb) * lsb

        half = 0.5 * self.drive.track_width / r
        rel = phi - qb
        wl, wr = rel - half * psi, rel + half * psi
        cpr = noise.encoder_counts_per_rad
        return Sensors(
            t=self.t,
            q_base=qb + fx.imu_pitch_bias_rad + rng.normal(0.0, noise.imu_pitch_std_rad),
            pitch_rate=q(dqb + rng.normal(0.0, noise.gyro_std_rad_s), noise.gyro_lsb_rad_s),
            gyro=tuple(
                q(w + rng.normal(0.0, noise.gyro_std_rad_s), noise.gyro_lsb_rad_s) for w in gyro
            ),
            specific_force=tuple(
                q(f + rng.normal(0.0, noise.accel_std_m_s2), noise.accel_lsb_m_s2)
                for f in (0.0, f_y, f_z)
            ),
            wheel_left=round(wl * cpr) / cpr,
            wheel_right=round(wr * cpr) / cpr,
            wheel_left_rate=dphi - dqb - half * dpsi,
            wheel_right_rate=dphi - dqb + half * dpsi,
            joints=self.joints
            + self._enc_offset
            + rng.normal(0.0, noise.joint_std_rad, len(self.joints)),
            wheel_current_left=self.applied_current[0],
            wheel_current_right=self.applied_current[1],
        )
