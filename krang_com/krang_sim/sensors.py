"""The one sensor model of the simulated Krang: what the devices report of a plant's true motion,
and when the drives apply what they were asked for.

Every plant (``krang_sim.plant``) gives its true ``Motion``; ``SensorModel`` turns it into what
the robot's devices report, for the offline closed loop (``control_sample``: the controller's
sample, the hot path) and for the CAN device emulators of ``sim_krang`` (``encoders``,
``joint_encoders``, ``dmu_inputs``; the DMU emulator adds this model's noise and quantises with the
DBC's scales). The
resolutions are the hardware's, read from their one source: the DMU's LSB scales from the DBC
(``krang_can_bridge.protocols.dmu_imu.DmuCodec``), the wheel encoders' counts per radian from the
device map (config/can_devices.yaml). The sensor-side terms of ``krang_model.effects.ModelTerms``
(``imu_pitch_bias``: a pitch misalignment of the IMU; ``joint_offsets``: body-joint encoders
reading q + offset) are applied here and nowhere else.

``CommandDelay`` is the drives' transport delay (``ModelTerms.actuation_delay``), the same stage
in front of every plant: the current applied at time t is the one commanded at t - delay (whole
physics steps), zero before the first command.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from krang_adrc_controller.samples import ControlSample
from krang_model.drivetrain import command_delay_steps


@dataclass(frozen=True)
class DeviceScales:
    """The resolutions of the robot's sensors, from the device map and its DBC."""

    gyro_lsb_rad_s: float
    accel_lsb_m_s2: float
    encoder_counts_per_rad: float  # wheel encoder counts per wheel radian (through the gearbox)


@functools.lru_cache(maxsize=None)
def device_scales(devices_file: str | None = None) -> DeviceScales:
    """The DMU's LSBs (its DBC) and the wheel encoders' resolution (the device map)."""
    from krang_can_bridge.config import load_devices
    from krang_can_bridge.protocols import load_dbc
    from krang_can_bridge.protocols.dmu_imu import DmuCodec

    devices = load_devices(devices_file) if devices_file else load_devices()
    dmu = DmuCodec(load_dbc(devices.dbc_path))
    return DeviceScales(
        dmu.rate_lsb_rad_s, dmu.accel_lsb_m_s2, float(devices.wheels.counts_per_wheel_rad)
    )


@dataclass
class SensorNoise:
    """Noise and resolution of the hardware sensors (krang_model/README.md, Sensors)."""

    imu_pitch_std_rad: float = math.radians(0.1)
    gyro_std_rad_s: float = 0.002
    gyro_lsb_rad_s: float = field(default_factory=lambda: device_scales().gyro_lsb_rad_s)
    accel_lsb_m_s2: float = field(default_factory=lambda: device_scales().accel_lsb_m_s2)
    accel_std_m_s2: float = 0.02
    encoder_counts_per_rad: float = field(
        default_factory=lambda: device_scales().encoder_counts_per_rad
    )
    joint_std_rad: float = 1e-4


def quiet_noise() -> SensorNoise:
    """No noise, the devices' resolutions kept (for exact comparisons)."""
    return SensorNoise(
        imu_pitch_std_rad=0.0, gyro_std_rad_s=0.0, accel_std_m_s2=0.0, joint_std_rad=0.0
    )


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


# ----------------------------------------------------------------------------- command delay


class CommandDelay:
    """The drives' transport delay in front of a stepping plant (``krang_model.drivetrain.
    HeldCommand`` states it on arrays of times): ``push(command)`` once per physics step returns
    the command applied in that step, the one pushed ``command_delay_steps(delay, dt)`` steps
    before, zero before the first."""

    def __init__(self, delay_s: float, dt: float, zero=(0.0, 0.0)):
        self.steps = command_delay_steps(delay_s, dt)
        self.active = self.steps > 0  # else ``push`` returns its argument
        self.zero = zero
        self._queue = deque()

    def push(self, command):
        if not self.steps:
            return command
        q = self._queue
        q.append(command)
        return q.popleft() if len(q) > self.steps else self.zero


# ----------------------------------------------------------------------------- the sensor model


class SensorModel:
    """The devices' view of a plant's motion, with the sensor-side terms of ``ModelTerms``.

    ``sample(motion)`` gives every device's reading (``Sensors``); ``control_sample(plant)`` the
    controller's sample only, fast: it reads the plant's ``wheel_pitch()`` and draws its noise in
    blocks (pitch, gyro-rate quantisation, encoder counts, joint noise; with zero noise it equals
    ``sample_from_sensors(sample(plant.motion()))``). The noise figures are read once, when
    the model is made."""

    _BLOCK = 4096

    def __init__(self, robot, terms=None, noise: SensorNoise | None = None, seed: int = 0):
        self.robot = robot
        self.noise = noise if noise is not None else SensorNoise()
        self.imu_pitch_bias = float(terms.imu_pitch_bias) if terms is not None else 0.0
        offsets = dict(terms.joint_offsets) if terms is not None else {}
        self.joint_offset = np.zeros(len(robot.pose_joints))
        for name, value in offsets.items():
            self.joint_offset[robot.pose_joints.index(name)] += float(value)
        self._has_offset = bool(np.any(self.joint_offset))
        self.rng = np.random.default_rng(seed)
        n = self.noise
        self._fast = (
            self.imu_pitch_bias,
            n.imu_pitch_std_rad,
            n.gyro_std_rad_s,
            n.gyro_lsb_rad_s,
            n.encoder_counts_per_rad,
        )
        self._nrow = self._BLOCK
        self._scalars = None
        self._jnoise = None

    # --- what the emulated devices are given ----------------------------------------------------
    def encoders(self, motion):
        """(left, right) wheel encoder angles (rad, quantised to counts) and rates (rad/s)."""
        cpr = self.noise.encoder_counts_per_rad
        return (
            round(motion.wheel_left * cpr) / cpr,
            round(motion.wheel_right * cpr) / cpr,
        ), (motion.wheel_left_rate, motion.wheel_right_rate)

    def joint_encoders(self, joints) -> np.ndarray:
        """What the body joints' encoders read of the true `joints` (rad, pose order): the offset
        of ``joint_offsets`` and the encoders' noise."""
        return (
            joints
            + self.joint_offset
            + self.rng.normal(0.0, self.noise.joint_std_rad, len(joints))
        )

    def dmu_inputs(self, motion):
        """What the DMU emulator is given (``frames_from_pitch``): the pitch the misaligned IMU
        sees, the pitch rate, and the specific force along the world's forward and up directions
        (from the plant's, in the base frame, at the true pitch)."""
        qb = motion.q_base
        s, c = math.sin(qb), math.cos(qb)
        _, f_y, f_z = motion.specific_force
        return qb + self.imu_pitch_bias, motion.dq_base, s * f_y - c * f_z, c * f_y + s * f_z

    # --- every device ---------------------------------------------------------------------------
    def sample(self, motion) -> Sensors:
        """Everything the devices report of `motion` (noise drawn one value at a time)."""
        noise, rng = self.noise, self.rng
        b = self.imu_pitch_bias
        # the bias is a pitch misalignment of the sensor: its y-z axes turn by b about x
        cb, sb = math.cos(b), math.sin(b)
        gx, gy, gz = motion.gyro
        fx, fy, fz = motion.specific_force
        gyro = (gx, cb * gy - sb * gz, sb * gy + cb * gz)
        force = (fx, cb * fy - sb * fz, sb * fy + cb * fz)
        glsb, alsb = noise.gyro_lsb_rad_s, noise.accel_lsb_m_s2

        def q(v, lsb):
            return round(v / lsb) * lsb

        q_base = motion.q_base + b + rng.normal(0.0, noise.imu_pitch_std_rad)
        pitch_rate = q(motion.dq_base + rng.normal(0.0, noise.gyro_std_rad_s), glsb)
        gyro = tuple(q(w + rng.normal(0.0, noise.gyro_std_rad_s), glsb) for w in gyro)
        force = tuple(q(f + rng.normal(0.0, noise.accel_std_m_s2), alsb) for f in force)
        (wl, wr), (dwl, dwr) = self.encoders(motion)
        joints = self.joint_encoders(motion.joints)
        il, ir = motion.applied_current
        return Sensors(motion.t, q_base, pitch_rate, gyro, force, wl, wr, dwl, dwr, joints, il, ir)

    # --- the controller's sample (hot path) -----------------------------------------------------
    def _refill(self, n_joints):
        rng = self.rng
        self._scalars = rng.standard_normal((self._BLOCK, 2)).tolist()
        self._jnoise = rng.standard_normal((self._BLOCK, n_joints)) * self.noise.joint_std_rad
        self._nrow = 0

    def control_sample(self, plant) -> ControlSample:
        """The controller's sample of `plant` now (``ControlSample``)."""
        if self._nrow >= self._BLOCK:
            self._refill(len(plant.joints))
        k = self._nrow
        self._nrow = k + 1
        n0, n1 = self._scalars[k]
        bias, imu_std, gyro_std, lsb, cpr = self._fast
        t, qb, dqb, wl, wr, dwl, dwr = plant.wheel_pitch()
        joints = plant.joints + self.joint_offset if self._has_offset else plant.joints
        return ControlSample(
            t,
            qb + bias + imu_std * n0,
            round((dqb + gyro_std * n1) / lsb) * lsb,
            round(wl * cpr) / cpr,
            round(wr * cpr) / cpr,
            dwl,
            dwr,
            joints + self._jnoise[k],
            plant.joints_moving,
        )
