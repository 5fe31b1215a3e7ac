"""The CAN bridge core: frames in, robot state out; commands in, clamped frames out. No ROS here.

Feed every received frame to `on_frame(msg, now, bus)`. The core keeps the latest wheel states (AMC
TPDOs), body joint states (PowerCube replies) and IMU samples (paired by sequence number, filtered
to base pitch), counts malformed and unknown frames, and watches each device for silence.

Safety rules, all enforced here so the ROS shell cannot get them wrong:
- a command beyond the configured limits never reaches the bus: wheel currents are clamped to the
  configured limit and the drive's peak, joint targets to the joint limits (in module coordinates,
  after float32 rounding), module speeds and accelerations to the module's datasheet limits;
- NaN/inf commands are rejected with a logged reason: no frame for a joint; the two wheel efforts
  are one command (the wheels are one machine), so unless both are finite and there are exactly
  two, BOTH wheels get zero current; every rejection is counted, its reason kept, and
  `diagnostics` WARNs for REJECTION_WARN_S after it;
- a FAULT statusword or an EMCY (error code not 0) of ANY drive, or a started drive leaving
  OPERATION_ENABLED, latches a drive fault (`fault_reason`): zero current on both wheels and no
  joint motion until `clear_fault`, which the node calls only after a DS402 fault reset and enable
  sequence left every drive OPERATION_ENABLED again (`recover_status`);
- the watchdog frames the drives consume (`watchdog_frames`: heartbeat or node-guarding requests,
  see config.WatchdogConfig) are produced only while the wheel command loop ran within
  `wheels.watchdog.alive_timeout_s`: a hung bridge stops beating and the drives stop by
  themselves;
- `motion_allowed(now)` is False while a drive fault is latched, any required device is silent,
  the IMU filter is not initialised, or an `inhibit` is set (e.g. by the node until the AMC
  start-up succeeded); then
  wheel commands are zero current and joint commands produce no frames;
- an effort command older than `wheels.command_timeout_s` is replaced by zero current
  (`wheel_command_frames`), because an AMC drive holds its last current forever; the node sends
  the current frames from each command, and a watchdog timer sends zero current once the command
  is stale or motion is not allowed (`wheel_watchdog_frames`, within `WATCHDOG_QUIET_PERIODS`
  refresh periods); it never repeats a command in force.

`on_frame` returns which sample a frame completed (`IMU_SAMPLE`: the DMU's rates and
accelerations of one sequence number; `WHEEL_SAMPLE`: position, velocity and current of every
drive since the last one), so the node publishes each sample as soon as its frames are in.

Every produced frame is a `BusFrame(bus, msg)`: the same ids are used on several buses (left and
right arm).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, NamedTuple

import can
import numpy as np

from krang_can_bridge.config import BodyJointConfig, CanDevicesConfig, PowerCubeModuleConfig
from krang_can_bridge.imu_filter import ImuPitchEstimator, PitchEstimate
from krang_can_bridge.protocols import ProtocolError, load_dbc
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols import powercube as pc
from krang_can_bridge.protocols.dmu_imu import DmuAccelerations, DmuCodec, DmuRates
from krang_ros.names import BRIDGE_RECOVER

logger = logging.getLogger('krang_can_bridge')

OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/DiagnosticStatus levels
NMT_ID = 0x000
EMCY_BASE, SDO_RESPONSE_BASE, SDO_REQUEST_BASE, HEARTBEAT_BASE = 0x080, 0x580, 0x600, 0x700
REJECTION_WARN_S = 10.0  # /diagnostics WARNs this long after a rejected command
# The watchdog timer sends only when no current frame went out for this many refresh periods
# (1 / wheels.command_rate_hz): commands that flow at least that often are never doubled.
WATCHDOG_QUIET_PERIODS = 2.0
IMU_SAMPLE, WHEEL_SAMPLE = 'imu', 'wheels'  # what on_frame completed
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
class _Device:
    name: str
    required: bool
    timeout_s: float
    last_seen: float | None = None
    malformed: int = 0

    def silent(self, now: float) -> bool:
        return self.last_seen is None or now - self.last_seen > self.timeout_s


@dataclass
class _ModuleState:
    joint: BodyJointConfig
    module: PowerCubeModuleConfig
    device: _Device
    position: float | None = None  # module coordinates
    velocity: float | None = None
    short_state: int | None = None


@dataclass
class _WheelState:
    codec: amc_proto.AmcDriveCodec
    device: _Device
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
    fresh: set = field(default_factory=set)  # TPDO kinds received since the last wheel sample


@dataclass
class _Counters:
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


def _float32_within(value: float, lower: float, upper: float) -> float:
    """`value` clamped to [lower, upper] such that its float32 rounding also stays inside."""
    v = np.float32(min(upper, max(lower, value)))
    if float(v) > upper:
        v = np.nextafter(v, np.float32(-np.inf))
    if float(v) < lower:
        v = np.nextafter(v, np.float32(np.inf))
    return float(v)


class BridgeCore:
    """State and command logic of the CAN bridge (see the module docstring)."""

    def __init__(
        self,
        config: CanDevicesConfig,
        clock: Callable[[], float] = time.monotonic,
        imu_sample_period_s: float = 0.0,
    ):
        self.config = config
        self.clock = clock
        dbc = load_dbc(config.dbc_path)
        self.dmu = DmuCodec(dbc)
        self.counters = _Counters()
        self._started_at = clock()
        self._log_times: dict[str, float] = {}
        self._inhibits: dict[str, str] = {}

        w = config.wheels
        self._wheels: dict[str, _WheelState] = {}
        self._wheel_by_id: dict[int, _WheelState] = {}
        self._wheel_echo_ids: set[int] = set()
        self._canopen_ids: set[int] = set()
        for drive in w.drives:
            codec = amc_proto.AmcDriveCodec(drive, w, dbc)
            state = _WheelState(
                codec, _Device(f'amc/{drive.joint}', w.required, w.silence_timeout_s)
            )
            self._wheels[drive.joint] = state
            for fid in codec.feedback_ids:
                self._wheel_by_id[fid] = state
            self._wheel_echo_ids |= set(codec.command_ids) | {SDO_REQUEST_BASE + drive.node_id}
            self._canopen_ids |= {
                SDO_RESPONSE_BASE + drive.node_id,
                HEARTBEAT_BASE + drive.node_id,
            }
        self._emcy_ids = {EMCY_BASE + s.codec.drive.node_id: s for s in self._wheels.values()}
        self._wheel_echo_ids.add(amc_proto.HEARTBEAT_BASE + w.watchdog.node_id)  # our heartbeat
        self._wheel_command: tuple[float, float, float] | None = None  # (left, right, time)
        self._command_loop_at: float | None = None
        self._wheel_sent_at: float | None = None
        self._fault = ''

        self._imu_device = _Device('imu', config.imu.required, config.imu.silence_timeout_s)
        # the filter steps by the DMU's sequence counter (imu_filter.ImuPitchEstimator)
        self._imu_estimator = ImuPitchEstimator(config.imu, imu_sample_period_s)
        self._imu_rates: DmuRates | None = None
        self._imu_accel: DmuAccelerations | None = None
        self._imu_snapshot: ImuSnapshot | None = None
        self._last_stream_toggle: float | None = None

        pcfg = config.powercube
        self._poll_frames: list[BusFrame] | None = None
        self._modules: dict[tuple[str, int], _ModuleState] = {}
        for joint in pcfg.joints:
            for m in joint.modules:
                dev = _Device(
                    f'powercube/{joint.joint}/{m.bus}:{m.module_id}',
                    pcfg.required,
                    pcfg.silence_timeout_s,
                )
                self._modules[(m.bus, m.module_id)] = _ModuleState(joint, m, dev)

    # ---- helpers --------------------------------------------------------------------------------
    def _now(self, now: float | None) -> float:
        return self.clock() if now is None else now

    def _log(
        self, key: str, text: str, level: int = logging.WARNING, period_s: float = 1.0
    ) -> None:
        """Log at most once per `period_s` per key (a 500 Hz NaN stream must not flood the log)."""
        t = self.clock()
        if t - self._log_times.get(key, -math.inf) >= period_s:
            self._log_times[key] = t
            logger.log(level, text)

    @property
    def devices(self) -> list[_Device]:
        return (
            [s.device for s in self._wheels.values()]
            + [self._imu_device]
            + [m.device for m in self._modules.values()]
        )

    def _bus_of(self, msg: can.Message, bus: str | None) -> str | None:
        if bus is not None:
            return bus
        return self.config.bus_for_channel(msg.channel) if msg.channel is not None else None

    # ---- receive --------------------------------------------------------------------------------
    def on_frame(
        self, msg: can.Message, now: float | None = None, bus: str | None = None
    ) -> str | None:
        """Consume one received frame; IMU_SAMPLE or WHEEL_SAMPLE when it completed one, else
        None. Never raises on bad input: it is counted instead."""
        now = self._now(now)
        bus = self._bus_of(msg, bus)
        c = self.counters
        c.frames += 1
        if msg.is_error_frame:
            c.error_frames[bus] = c.error_frames.get(bus, 0) + 1
            return None
        aid = msg.arbitration_id
        try:
            if bus == self.config.wheels.bus and aid in self._wheel_by_id:
                return self._on_wheel(self._wheel_by_id[aid], msg, now)
            elif bus == self.config.imu.bus and aid in self.dmu.feedback_ids:
                return self._on_imu(msg, now)
            elif (
                bus is not None
                and pc.ACK_BASE < aid <= pc.ACK_BASE + pc.MODULE_ID_MASK
                and (bus, aid & pc.MODULE_ID_MASK) in self._modules
            ):
                self._on_module(self._modules[(bus, aid & pc.MODULE_ID_MASK)], msg, now)
            elif bus == self.config.wheels.bus and aid in self._emcy_ids:
                self._on_emcy(self._emcy_ids[aid], msg)
            elif self._is_echo(bus, aid):
                c.echoes += 1
            elif bus == self.config.wheels.bus and aid in self._canopen_ids:
                c.canopen += 1
            else:
                c.unknown += 1
                c.last_unknown = f'0x{aid:03X} on {bus} ({len(msg.data)} bytes)'
        except ProtocolError as exc:
            c.malformed += 1
            c.last_malformed = f'{bus} 0x{aid:03X}: {exc}'
            self._log('malformed', f'malformed frame {c.last_malformed}')
        except Exception as exc:  # noqa: BLE001 - the bridge must survive any frame
            c.malformed += 1
            c.last_malformed = f'{bus} 0x{aid:03X}: unexpected {type(exc).__name__}: {exc}'
            self._log('malformed', f'malformed frame {c.last_malformed}', logging.ERROR)
        return None

    def received_ids(self, bus: str) -> frozenset[int]:
        """The ids the core (and the AMC start-up's SDO client) reads on `bus`: the drives'
        TPDOs, EMCYs, SDO responses and heartbeats, the DMU's samples, the PowerCube replies.
        Everything else there is a host's frame (ours looped back on udp_multicast) or unknown;
        the node lets the kernel drop it (bus_io.receive_only), so `counters.unknown` counts only
        what passes a bus without a kernel filter."""
        ids = {pc.ACK_BASE + module_id for b, module_id in self._modules if b == bus}
        if bus == self.config.wheels.bus:
            ids |= set(self._wheel_by_id) | set(self._emcy_ids) | self._canopen_ids
        if bus == self.config.imu.bus:
            ids |= self.dmu.feedback_ids
        return frozenset(ids)

    def _is_echo(self, bus: str | None, aid: int) -> bool:
        """Frames a host sends (ours looped back by udp_multicast, or another host's)."""
        if aid == NMT_ID:
            return True
        if bus == self.config.wheels.bus and aid in self._wheel_echo_ids:
            return True
        if bus == self.config.imu.bus and aid in self.dmu.command_ids:
            return True
        return pc.is_host_frame(aid)

    def _on_wheel(self, state: _WheelState, msg: can.Message, now: float) -> str | None:
        try:
            reading = state.codec.decode(msg)
        except ProtocolError:
            state.device.malformed += 1
            raise
        state.statusword = reading.statusword
        if reading.kind == 'statusword':
            state.drive_status, state.drive_status_at = reading.statusword, now
            self._check_drive_state(state)
        if reading.kind == 'position':
            state.position = reading.value
        elif reading.kind == 'velocity':
            state.velocity = reading.value
        elif reading.kind == 'current':
            state.current = reading.value
        state.device.last_seen = now
        state.fresh.add(reading.kind)
        if all(WHEEL_SAMPLE_KINDS <= w.fresh for w in self._wheels.values()):
            for w in self._wheels.values():
                w.fresh.clear()
            return WHEEL_SAMPLE
        return None

    def _on_emcy(self, state: _WheelState, msg: can.Message) -> None:
        """An EMCY latches a drive fault unless its error code is 0 (DS301 "error reset")."""
        data = bytes(msg.data)
        state.emcy = data.hex()
        code = int.from_bytes(data[:2], 'little') if len(data) >= 2 else None
        joint = state.codec.drive.joint
        if code == 0:
            self._log(f'emcy{joint}', f'{joint}: EMCY error reset', logging.INFO)
            return
        text = f'0x{code:04X}' if code is not None else f'malformed ({data.hex()})'
        self._latch_fault(f'{joint}: EMCY {text}, data {data.hex()}')

    def _check_drive_state(self, state: _WheelState) -> None:
        joint, sw = state.codec.drive.joint, state.drive_status
        name = amc_proto.drive_state(sw)
        if name == 'FAULT':
            state.armed = False
            self._latch_fault(f'{joint}: drive in FAULT (statusword 0x{sw:04X})')
        elif name == 'OPERATION_ENABLED':
            state.armed = state.started
        elif state.armed:
            state.armed = False
            self._latch_fault(
                f'{joint}: drive left OPERATION_ENABLED for {name} (statusword 0x{sw:04X})'
            )

    def _latch_fault(self, reason: str) -> None:
        """The first reason stays until clear_fault; later ones are logged."""
        if not self._fault:
            self._fault = reason
            self.counters.drive_faults += 1
            logger.error(f'drive fault latched, both wheels at zero current: {reason}')
        else:
            self._log(
                f'fault:{reason}', f'drive fault (already latched): {reason}', logging.ERROR, 5.0
            )

    # ---- drive faults ---------------------------------------------------------------------------
    @property
    def fault_reason(self) -> str:
        """The latched drive fault, '' when none."""
        return self._fault

    def drive_started(self, joint: str, started: bool) -> None:
        """The node's start-up/recovery sequence for `joint` finished (True) or is about to run
        (False: its transitions are not faults)."""
        state = self._wheels[joint]
        state.started = started
        state.armed = False

    def recover_status(self, since: float) -> tuple[bool | None, str]:
        """After a fault reset and enable sequence that ended at `since`: (True, '') once every
        drive has reported OPERATION_ENABLED since; (False, reason) as soon as one reports FAULT;
        (None, what is awaited) otherwise."""
        waiting = []
        for joint, w in self._wheels.items():
            if w.drive_status_at is None or w.drive_status_at < since:
                waiting.append(f'{joint}: no statusword since the enable sequence')
                continue
            name = amc_proto.drive_state(w.drive_status)
            if name == 'FAULT':
                return False, (
                    f'{joint} still reports FAULT (statusword 0x{w.drive_status:04X}) '
                    'after the fault reset'
                )
            if name != 'OPERATION_ENABLED':
                waiting.append(f'{joint}: {name} after the enable sequence')
        return (None, '; '.join(waiting)) if waiting else (True, '')

    def clear_fault(self) -> None:
        """Unlatch (only after recover_status said True: see the node's recover service)."""
        if self._fault:
            logger.warning(f'drive fault cleared by recover: {self._fault}')
        self._fault = ''
        for w in self._wheels.values():
            w.emcy = None

    def _on_imu(self, msg: can.Message, now: float) -> str | None:
        try:
            sample = self.dmu.decode(msg)
        except ProtocolError:
            self._imu_device.malformed += 1
            raise
        self._imu_device.last_seen = now
        if isinstance(sample, DmuRates):
            self._imu_rates = sample
        else:
            self._imu_accel = sample
        r, a = self._imu_rates, self._imu_accel
        if r is None or a is None or r.sequence != a.sequence:
            return None
        self._imu_rates = self._imu_accel = None  # one filter update per paired sample
        est: PitchEstimate = self._imu_estimator.update(
            (r.x, r.y, r.z), (a.x, a.y, a.z), now, r.sequence
        )
        w = self._imu_estimator.corrected_rates((r.x, r.y, r.z))
        self._imu_snapshot = ImuSnapshot(
            est.pitch,
            est.pitch_rate,
            (float(w[0]), float(w[1]), float(w[2])),
            (a.x, a.y, a.z),
            est.ready,
            est.variance,
            now,
        )
        return IMU_SAMPLE

    def _on_module(self, state: _ModuleState, msg: can.Message, now: float) -> None:
        try:
            reply = pc.decode_reply(msg)
        except ProtocolError:
            state.device.malformed += 1
            raise
        if reply.command == pc.GET_PARAM and reply.selector == pc.ACT_FPOS:
            state.position = float(reply.value)
        elif reply.command == pc.GET_PARAM and reply.selector == pc.ACT_FVEL:
            state.velocity = float(reply.value)
        elif reply.command == pc.SET_MOTION:
            state.position = float(reply.value)
            state.short_state = reply.short_state
        state.device.last_seen = now

    # ---- health ---------------------------------------------------------------------------------
    def silent_devices(self, now: float | None = None) -> list[str]:
        """Names of devices (required or not) not heard from within their timeout."""
        now = self._now(now)
        return [d.name for d in self.devices if d.silent(now)]

    def inhibit(self, key: str, reason: str | None) -> None:
        """Block motion for a reason outside the frames (e.g. an AMC start-up that failed); None
        clears it."""
        if reason is None:
            self._inhibits.pop(key, None)
        else:
            self._inhibits[key] = reason

    def motion_allowed(self, now: float | None = None) -> bool:
        now = self._now(now)
        if self._fault or self._inhibits:
            return False
        if any(d.required and d.silent(now) for d in self.devices):
            return False
        if self.config.imu.required and (
            self._imu_snapshot is None or not self._imu_snapshot.ready
        ):
            return False
        return True

    # ---- wheel commands -------------------------------------------------------------------------
    def wheel_current_limit_a(self, joint: str) -> float:
        """The drive train's current limit, or the drive's peak if lower."""
        return min(
            self.config.wheels.drivetrain.current_limit,
            self._wheels[joint].codec.drive.peak_current_a,
        )

    def _reject(self, reason: str, now: float) -> None:
        c = self.counters
        c.rejected_commands += 1
        c.last_rejection, c.last_rejection_at = reason, now
        self._log(f'reject:{reason.split(":")[0]}', f'rejected command: {reason}')

    def _wheel_efforts(self, efforts, now: float) -> tuple[float, ...] | None:
        """The efforts as floats if they are one valid command (one finite value per wheel), else
        None with the rejection recorded."""
        joints = self.config.wheel_joint_names
        try:
            values = list(efforts)
        except TypeError:
            values = None
        if values is None or len(values) != len(joints):
            n = 'no sequence' if values is None else f'{len(values)} values'
            self._reject(f'wheels: need [{", ".join(joints)}], got {n} -> 0 A on both', now)
            return None
        out = []
        for joint, v in zip(joints, values):
            try:
                x = float(v)
            except (TypeError, ValueError, OverflowError):
                x = math.nan
            if not math.isfinite(x):
                self._reject(f'wheels: {joint} effort {v!r} is not finite -> 0 A on both', now)
                return None
            out.append(x)
        return tuple(out)

    def wheel_current_frames(
        self, effort_left_Nm: float, effort_right_Nm: float, now: float | None = None
    ) -> list[BusFrame]:
        """RPDO current frames for efforts at the wheels [N m], clamped; zero current on both when
        motion is not allowed or either effort is invalid."""
        now = self._now(now)
        efforts = self._wheel_efforts((effort_left_Nm, effort_right_Nm), now)
        allowed = efforts is not None and self.motion_allowed(now)
        frames = []
        for joint, effort in zip(self.config.wheel_joint_names, efforts or (0.0, 0.0)):
            amps = 0.0
            if allowed:
                requested = self.config.wheels.effort_to_current(effort)
                limit = self.wheel_current_limit_a(joint)
                amps = min(limit, max(-limit, requested))
                if amps != requested:
                    self.counters.clamped_commands += 1
                    self._log(
                        f'clamp{joint}',
                        f'{joint}: {requested:.2f} A clamped to {amps:.2f} A',
                        logging.INFO,
                    )
            frames.append(
                BusFrame(
                    self.config.wheels.bus, self._wheels[joint].codec.encode_current_command(amps)
                )
            )
        return frames

    def set_wheel_effort_command(self, efforts, now: float | None = None) -> None:
        """Remember the latest effort command [left, right] N m (sent by `wheel_command_frames`
        while it is fresh); an invalid one is rejected and replaced by zero on both wheels."""
        now = self._now(now)
        valid = self._wheel_efforts(efforts, now)
        left, right = valid if valid is not None else (0.0, 0.0)
        self._wheel_command = (left, right, now)

    def wheel_command_frames(self, now: float | None = None) -> list[BusFrame]:
        """The current frames of the latest command if younger than command_timeout_s, else zero
        current (sent on each command, and by `wheel_watchdog_frames`)."""
        now = self._now(now)
        self._command_loop_at = self._wheel_sent_at = now
        cmd = self._wheel_command
        if cmd is None or now - cmd[2] > self.config.wheels.command_timeout_s:
            return self.wheel_current_frames(0.0, 0.0, now)
        return self.wheel_current_frames(cmd[0], cmd[1], now)

    def wheel_watchdog_frames(self, now: float | None = None) -> list[BusFrame]:
        """The wheel command loop's timer: zero current once the latest command is stale (older
        than command_timeout_s) or motion is not allowed, repeated every WATCHDOG_QUIET_PERIODS
        refresh periods; [] otherwise. A command in force is never repeated: its frames went out
        with it, the drive holds that current, and a repeat would only be a frame that answers
        no sample (in lockstep simulation sim_krang would take it for the controller's answer
        and run on while the controller is late). Either way the loop counts as running, which
        keeps the drives' watchdog fed."""
        now = self._now(now)
        self._command_loop_at = now
        quiet = WATCHDOG_QUIET_PERIODS / self.config.wheels.command_rate_hz
        if self._wheel_sent_at is not None and now - self._wheel_sent_at < quiet:
            return []
        cmd = self._wheel_command
        in_force = (
            cmd is not None
            and now - cmd[2] <= self.config.wheels.command_timeout_s
            and self.motion_allowed(now)
        )
        return [] if in_force else self.wheel_command_frames(now)

    # ---- joint commands -------------------------------------------------------------------------
    def _module_target(
        self, joint: BodyJointConfig, module: PowerCubeModuleConfig, q: float
    ) -> float:
        lower, upper = joint.module_limits(module)
        return _float32_within(module.sign * q, lower, upper)

    def joint_position_frames(
        self, targets: Mapping[str, float], now: float | None = None
    ) -> list[BusFrame]:
        """FRAMP moves to joint targets [rad] (URDF names), clamped; [] when motion is not allowed.

        Each commanded module gets TARGET_VEL and TARGET_ACC (the module type's limits) then
        SET_MOTION FRAMP, like pcio_group_setpos. Unknown names (e.g. the wheels) and non-finite
        targets are skipped and logged.
        """
        now = self._now(now)
        if not self.motion_allowed(now):
            if targets:
                self._log(
                    'joints_blocked', 'joint command dropped: motion not allowed (silent device)'
                )
            return []
        frames = []
        for name, q in targets.items():
            try:
                joint = self.config.powercube.joint(name)
            except KeyError:
                self._log(
                    f'unknown{name}',
                    f'joint command for unknown joint {name!r} ignored',
                    logging.INFO,
                    10.0,
                )
                continue
            try:
                q = float(q)
            except (TypeError, ValueError):
                q = math.nan
            if not math.isfinite(q):
                self._reject(f'{name}: non-finite target {q!r} -> no motion', now)
                continue
            if joint.clamp(q) != q:
                self.counters.clamped_commands += 1
                self._log(
                    f'clamp{name}',
                    f'{name}: target {q:.4f} clamped to [{joint.lower}, {joint.upper}]',
                    logging.INFO,
                )
            vel = _float32_within(joint.max_velocity_rad_s, 0.0, joint.max_velocity_rad_s)
            acc = _float32_within(
                joint.max_acceleration_rad_s2, 0.0, joint.max_acceleration_rad_s2
            )
            for m in joint.modules:
                frames += [
                    BusFrame(m.bus, pc.set_param(m.module_id, pc.TARGET_VEL, vel)),
                    BusFrame(m.bus, pc.set_param(m.module_id, pc.TARGET_ACC, acc)),
                    BusFrame(
                        m.bus,
                        pc.set_motion(m.module_id, pc.FRAMP_ACK, self._module_target(joint, m, q)),
                    ),
                ]
        return frames

    def watchdog_frames(self, now: float | None = None) -> list[BusFrame]:
        """The frames the drives' watchdog consumes (the bridge's heartbeat, or a guarding request
        per drive), or [] when the wheel command loop has not run within alive_timeout_s: a beat
        proves the control path is alive, not just that this process is."""
        now = self._now(now)
        wd, bus = self.config.wheels.watchdog, self.config.wheels.bus
        if (
            wd.mechanism == 'none'
            or self._command_loop_at is None
            or now - self._command_loop_at > wd.alive_timeout_s
        ):
            return []
        if wd.mechanism == 'heartbeat':
            return [BusFrame(bus, amc_proto.heartbeat_frame(wd))]
        return [
            BusFrame(bus, amc_proto.guarding_request(d.node_id)) for d in self.config.wheels.drives
        ]

    def poll_frames(self) -> list[BusFrame]:
        """GET_PARAM ACT_FPOS and ACT_FVEL for every module (modules only speak when asked); the
        same frames every time, encoded once."""
        if self._poll_frames is None:
            self._poll_frames = [
                BusFrame(bus, pc.get_param(module_id, param))
                for bus, module_id in self._modules
                for param in (pc.ACT_FPOS, pc.ACT_FVEL)
            ]
        return list(self._poll_frames)

    def startup_frames(self) -> list[BusFrame]:
        """PowerCube start-up: RESET (clears HALT), soft limits MIN/MAX_FPOS in module coordinates
        (as the robot's init script set them), TARGET_VEL/TARGET_ACC. The AMC start-up needs SDO
        replies: see amc.run_startup."""
        frames = []
        for st in self._modules.values():
            lower, upper = st.joint.module_limits(st.module)
            b, i = st.module.bus, st.module.module_id
            frames += [
                BusFrame(b, pc.simple_command(i, pc.RESET)),
                BusFrame(b, pc.set_param(i, pc.MIN_FPOS, _float32_within(lower, lower, upper))),
                BusFrame(b, pc.set_param(i, pc.MAX_FPOS, _float32_within(upper, lower, upper))),
                BusFrame(
                    b,
                    pc.set_param(
                        i,
                        pc.TARGET_VEL,
                        _float32_within(
                            st.joint.max_velocity_rad_s, 0.0, st.joint.max_velocity_rad_s
                        ),
                    ),
                ),
                BusFrame(
                    b,
                    pc.set_param(
                        i,
                        pc.TARGET_ACC,
                        _float32_within(
                            st.joint.max_acceleration_rad_s2, 0.0, st.joint.max_acceleration_rad_s2
                        ),
                    ),
                ),
            ]
        return frames

    def imu_stream_frames(self, now: float | None = None) -> list[BusFrame]:
        """The DMU stream toggle, only after the IMU has been silent for stream_toggle_retry_s (it
        is a toggle: sending it to a streaming DMU would stop it)."""
        now = self._now(now)
        quiet_since = max(
            self._started_at,
            self._imu_device.last_seen if self._imu_device.last_seen is not None else -math.inf,
            self._last_stream_toggle if self._last_stream_toggle is not None else -math.inf,
        )
        if now - quiet_since < self.config.imu.stream_toggle_retry_s:
            return []
        self._last_stream_toggle = now
        return [BusFrame(self.config.imu.bus, self.dmu.stream_toggle())]

    # ---- state ----------------------------------------------------------------------------------
    # A silent device's last reading is left out of the state, not republished under a fresh stamp:
    # the controller then sees its input go stale and stops (its own stale_timeout_s), as the
    # bridge does.
    def joint_state(self, now: float | None = None) -> JointStateSnapshot:
        """Joints whose devices have all been heard from within their silence timeouts."""
        now = self._now(now)
        names, pos, vel, eff = [], [], [], []
        for joint in self.config.powercube.joints:
            states = [self._modules[(m.bus, m.module_id)] for m in joint.modules]
            if any(s.position is None or s.device.silent(now) for s in states):
                continue
            names.append(joint.joint)
            pos.append(sum(s.module.sign * s.position for s in states) / len(states))
            vel.append(
                sum(s.module.sign * s.velocity for s in states) / len(states)
                if all(s.velocity is not None for s in states)
                else math.nan
            )
            eff.append(math.nan)
        for joint, w in self._wheels.items():
            if w.position is None or w.device.silent(now):
                continue
            names.append(joint)
            pos.append(w.position)
            vel.append(w.velocity if w.velocity is not None else math.nan)
            eff.append(
                self.config.wheels.current_to_effort(w.current)
                if w.current is not None
                else math.nan
            )
        return JointStateSnapshot(names, pos, vel, eff)

    def wheel_state(self, joint: str) -> _WheelState:
        return self._wheels[joint]

    def imu_state(self, now: float | None = None) -> ImuSnapshot | None:
        """The filtered IMU, or None while the DMU is silent."""
        return None if self._imu_device.silent(self._now(now)) else self._imu_snapshot

    # ---- diagnostics ----------------------------------------------------------------------------
    def diagnostics(self, now: float | None = None) -> list[DiagnosticReport]:
        now = self._now(now)
        c = self.counters
        silent = [d for d in self.devices if d.silent(now)]
        allowed = self.motion_allowed(now)
        fault = (
            [f'drive fault latched: {self._fault} (call {BRIDGE_RECOVER})'] if self._fault else []
        )
        reports = [
            DiagnosticReport(
                'can_bridge: motion',
                OK if allowed else ERROR,
                'motion allowed'
                if allowed
                else 'motion disabled (zero wheel current, no joint motion): '
                + (
                    '; '.join(
                        fault
                        + list(self._inhibits.values())
                        + [f'{d.name} silent' for d in silent if d.required]
                    )
                    or 'IMU filter not initialised'
                ),
                {
                    'silent_devices': ', '.join(d.name for d in silent),
                    'inhibits': '; '.join(self._inhibits.values()),
                    'drive_fault': self._fault,
                    'drive_faults_latched': str(c.drive_faults),
                },
            )
        ]
        recent = c.last_rejection_at is not None and now - c.last_rejection_at <= REJECTION_WARN_S
        reports.append(
            DiagnosticReport(
                'can_bridge: commands',
                WARN if recent else OK,
                (
                    f'{c.rejected_commands} rejected commands, last: {c.last_rejection}'
                    if recent
                    else f'{c.rejected_commands} rejected commands, none in the last '
                    f'{REJECTION_WARN_S:.0f} s'
                    if c.rejected_commands
                    else 'no rejected commands'
                ),
                {
                    'rejected_commands': str(c.rejected_commands),
                    'last_rejection': c.last_rejection,
                    'last_rejection_age_s': ''
                    if c.last_rejection_at is None
                    else f'{now - c.last_rejection_at:.3f}',
                    'clamped_commands': str(c.clamped_commands),
                },
            )
        )
        reports.append(
            DiagnosticReport(
                'can_bridge: frames',
                WARN if c.malformed or c.unknown else OK,
                f'{c.malformed} malformed, {c.unknown} unknown of {c.frames}',
                {
                    'frames': str(c.frames),
                    'malformed': str(c.malformed),
                    'unknown': str(c.unknown),
                    'echoes': str(c.echoes),
                    'canopen': str(c.canopen),
                    'last_malformed': c.last_malformed,
                    'last_unknown': c.last_unknown,
                },
            )
        )
        wd = self.config.wheels.watchdog
        beating = (
            wd.mechanism != 'none'
            and self._command_loop_at is not None
            and now - self._command_loop_at <= wd.alive_timeout_s
        )
        reports.append(
            DiagnosticReport(
                'can_bridge: drive watchdog',
                OK if beating or wd.mechanism == 'none' else WARN,
                'off (mechanism none): the drives hold their last current if the bridge dies'
                if wd.mechanism == 'none'
                else f'{wd.mechanism} every {wd.period_ms} ms, drives stop {wd.timeout_ms} ms '
                f'after '
                'the last' + ('' if beating else ': WITHHELD, wheel command loop quiet'),
                {
                    'mechanism': wd.mechanism,
                    'node_id': str(wd.node_id),
                    'abort_connection_option': str(wd.abort_connection_option),
                },
            )
        )
        for bus in self.config.buses_in_use():
            n = c.error_frames.get(bus, 0)
            reports.append(
                DiagnosticReport(
                    f'can_bridge: bus {bus}',
                    WARN if n else OK,
                    f'{n} error frames',
                    {'error_frames': str(n)},
                )
            )
        for joint, w in self._wheels.items():
            state = amc_proto.drive_state(w.statusword) if w.statusword is not None else 'unknown'
            level = (
                STALE
                if w.device.silent(now)
                else OK
                if state == 'OPERATION_ENABLED'
                else ERROR
                if state == 'FAULT'
                else WARN
            )
            reports.append(
                DiagnosticReport(
                    f'can_bridge: {w.device.name}',
                    level,
                    f'drive {state}',
                    {
                        'position_rad': str(w.position),
                        'velocity_rad_s': str(w.velocity),
                        'current_a': str(w.current),
                        'emcy': str(w.emcy),
                        'malformed': str(w.device.malformed),
                    },
                )
            )
        imu = self._imu_snapshot
        level = (
            STALE
            if self._imu_device.silent(now)
            else (OK if imu is not None and imu.ready else WARN)
        )
        reports.append(
            DiagnosticReport(
                'can_bridge: imu',
                level,
                'silent' if level == STALE else ('ok' if level == OK else 'initialising'),
                {
                    'pitch_rad': str(imu.pitch if imu else None),
                    'malformed': str(self._imu_device.malformed),
                },
            )
        )
        for st in self._modules.values():
            not_ok = st.short_state is not None and st.short_state & pc.SHORT_NOT_OK
            level = STALE if st.device.silent(now) else (WARN if not_ok else OK)
            reports.append(
                DiagnosticReport(
                    f'can_bridge: {st.device.name}',
                    level,
                    'silent'
                    if level == STALE
                    else (
                        'module reports NOT_OK (error, not homed or halted)' if not_ok else 'ok'
                    ),
                    {
                        'position': str(st.position),
                        'short_state': str(st.short_state),
                        'malformed': str(st.device.malformed),
                    },
                )
            )
        return reports
