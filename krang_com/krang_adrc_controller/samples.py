"""The balancing controller's inputs and outputs: one synchronised sensor sample, the measured
joint motion, one step's output and the answer to an operator's request."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .detector import BalancedPoint


@dataclass(slots=True)
class ControlSample:
    """One synchronised sensor sample. Angles rad, rates rad/s, t in s (sensor clock)."""

    t: float
    q_base: float  # IMU pitch (krang_model/README.md convention)
    pitch_rate: float
    wheel_left: float  # wheel encoder angles relative to the body (rad, wheel side)
    wheel_right: float
    wheel_left_rate: float
    wheel_right_rate: float
    joints: np.ndarray  # body joints, pose order
    joints_moving: bool = False  # measured: the joints move now (not: a move is commanded)
    move_pending: bool = False  # the pose server's target is not reached yet (paused or not)
    # the accelerometer's pitch (krang_core.pitch.pitch_from_specific_force): gravity's direction,
    # true at rest and free of the gyro's drift; the detector averages it (NaN: not measured)
    gravity_pitch: float = math.nan


class JointMotion:
    """Whether the joints move, measured from their positions: the largest change over at least
    `window_s` above `speed_rad_s` times the time elapsed. A window, not one sample: the pose
    server streams targets at 20 Hz and the joints stop briefly between them, and a per-sample
    difference would be mostly encoder noise."""

    def __init__(self, speed_rad_s: float = 0.02, window_s: float = 0.1):
        self.speed = float(speed_rad_s)
        self.window = float(window_s)
        self._ref = None  # (t, joints) at the start of the current window
        self.moving = False

    def update(self, t: float, joints) -> bool:
        joints = np.asarray(joints, float)
        if self._ref is None or t < self._ref[0]:
            self._ref = (t, joints.copy())
            return self.moving
        elapsed = t - self._ref[0]
        if elapsed >= self.window:
            self.moving = bool(np.max(np.abs(joints - self._ref[1])) > self.speed * elapsed)
            self._ref = (t, joints.copy())
        return self.moving


@dataclass(slots=True)
class ControlOutput:
    mode: str
    torque_left: float  # N m at the wheel
    torque_right: float
    current_left: float  # A at the motor (positive drives x forward)
    current_right: float
    balanced_point: BalancedPoint | None
    theta: float  # CoM angle from vertical with the estimated beta (rad)
    x: float  # ground-referenced wheel position r (mean encoders + q_base), m
    f_hat_x: float
    f_hat_theta: float
    events: list = field(default_factory=list)
    dtheta: float = 0.0  # rad/s (IMU rate)
    dx: float = 0.0  # m/s
    x_ref: float = 0.0  # m, the position reference of STAND_UP/BALANCE
    psi: float = 0.0  # wheel radians
    saturated: bool = False
    balance_trim: float = 0.0  # rad, the balance-point observer's delta_hat (0 when it is off)
    balance_converged: bool = False  # BALANCE with a settled balance estimate (see step)
    move_points: tuple | list = ()  # BalancedPoints read on a move that ended at this step


@dataclass(frozen=True)
class Reply:
    """The answer to an operator's request: accepted or not, and why."""

    ok: bool
    message: str


def sample_from_sensors(
    sensors, joints_moving: bool = False, move_pending: bool = False
) -> ControlSample:
    """ControlSample from a ``krang_sim.physics.Sensors`` reading."""
    return ControlSample(
        sensors.t,
        sensors.q_base,
        sensors.pitch_rate,
        sensors.wheel_left,
        sensors.wheel_right,
        sensors.wheel_left_rate,
        sensors.wheel_right_rate,
        sensors.joints,
        joints_moving,
        move_pending,
    )
