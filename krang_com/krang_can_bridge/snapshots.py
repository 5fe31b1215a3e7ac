"""What the CAN bridge core takes in and gives out, and the state it keeps per device: frames to
send (tagged with their bus), the joint and IMU snapshots, diagnostic reports, device and drive
state, counters. No ROS here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import can
import numpy as np

from krang_can_bridge.config import BodyJointConfig, PowerCubeModuleConfig
from krang_can_bridge.protocols import amc as amc_proto

OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/DiagnosticStatus levels
IMU_SAMPLE, WHEEL_SAMPLE = 'imu', 'wheels'  # what BridgeCore.on_frame completed
WHEEL_SAMPLE_KINDS = frozenset({'position', 'velocity', 'current'})


class BusFrame(NamedTuple):
    bus: str
    msg: can.Message


class JointStateSnapshot(NamedTuple):
    """Joints with known values only (URDF names; body joints first, then wheels). efforts: the
    wheels' measured currents as torque at the wheel [N m] (krang_model.drivetrain), NaN for the
    body joints (not measured)."""

    names: list[str]
    positions: list[float]
    velocities: list[float]
    efforts: list[float]


class ImuSnapshot(NamedTuple):
    pitch: float  # q_base [rad], hardware convention
    pitch_rate: float  # filtered dq_base [rad/s]
    rates: tuple[float, float, float]  # bias-corrected, sensor axes [rad/s]
    specific_force: tuple[float, float, float]  # sensor axes [m/s^2]
    ready: bool
    pitch_variance: float
    stamp: float


class DiagnosticReport(NamedTuple):
    name: str
    level: int
    message: str
    values: dict


@dataclass
class Device:
    name: str
    required: bool
    timeout_s: float
    last_seen: float | None = None
    malformed: int = 0

    def silent(self, now: float) -> bool:
        return self.last_seen is None or now - self.last_seen > self.timeout_s


@dataclass
class ModuleState:
    joint: BodyJointConfig
    module: PowerCubeModuleConfig
    device: Device
    position: float | None = None  # module coordinates
    velocity: float | None = None
    short_state: int | None = None
    position_at: float | None = None  # when the position was read (the bridge's clock)


@dataclass
class WheelState:
    codec: amc_proto.AmcDriveCodec
    device: Device
    position: float | None = None
    velocity: float | None = None
    current: float | None = None
    statusword: int | None = None  # the leading bytes of any TPDO (diagnostics)
    # The statusword TPDO alone (mapped to 0x6041 by the driver; that the other TPDOs lead with it
    # is our reading, so no fault decision rests on them)
    drive_status: int | None = None
    drive_status_at: float | None = None
    emcy: str | None = None
    started: bool = False  # the node's start-up (or recovery) sequence enabled this drive
    armed: bool = False  # started and seen OPERATION_ENABLED: leaving it is a fault
    boots: int = 0  # DS301 boot-up messages seen (a start-up during which one came is void)
    fresh: set = field(default_factory=set)  # TPDO kinds received since the last wheel sample


@dataclass
class Counters:
    frames: int = 0
    malformed: int = 0
    unknown: int = 0
    echoes: int = 0
    canopen: int = 0
    rejected_commands: int = 0
    clamped_commands: int = 0
    error_frames: dict = field(default_factory=dict)
    last_malformed: str = ''
    last_unknown: str = ''
    last_rejection: str = ''
    last_rejection_at: float | None = None
    drive_faults: int = 0
    frozen_samples: int = 0  # DMU samples dropped as frozen (counter stuck or values repeated)
    last_frozen: str = ''


def float32_within(value: float, lower: float, upper: float) -> float:
    """`value` clamped to [lower, upper] such that its float32 rounding also stays inside."""
    v = np.float32(min(upper, max(lower, value)))
    if float(v) > upper:
        v = np.nextafter(v, np.float32(-np.inf))
    if float(v) < lower:
        v = np.nextafter(v, np.float32(np.inf))
    return float(v)
