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
- a FAULT statusword or an EMCY (error code not 0) of ANY drive, a started drive leaving
  OPERATION_ENABLED, or its boot-up message or an NMT state but OPERATIONAL (a reboot: its
  settings and watchdog gone), latches a drive fault (`fault_reason`): zero current on both
  wheels and no joint motion until `clear_fault`, which the node calls only after the start-up
  sequence (DS402 fault reset and enable) left every drive OPERATION_ENABLED again
  (`recover_status`);
- the watchdog frames the drives consume (`watchdog_frames`: heartbeat or node-guarding requests,
  see config.WatchdogConfig) are produced only while the wheel command loop ran within
  `wheels.watchdog.alive_timeout_s`: a hung bridge stops beating and the drives stop by
  themselves;
- a frozen DMU (sequence counter stuck, or values bit-identical for imu.frozen_after_s) counts as
  silent: its samples are dropped, not filtered or published;
- `motion_allowed(now)` is False while a drive fault is latched, any required device is silent
  (a PowerCube module only until it was first heard), the IMU filter is not initialised, or an
  `inhibit` is set (e.g. by the node until the AMC start-up succeeded); then wheel commands are
  zero current and joint commands produce no frames;
- a PowerCube module that answered and then falls silent latches an arm fault
  (arm_fault.ArmFaults), which does not stop the wheels: its joint stays in the joint state at
  its last position (velocity 0), commands to it produce no frames, the other joints move, until
  a recover finds every module answering;
- an effort command older than `wheels.command_timeout_s` is replaced by zero current
  (`wheel_command_frames`), because an AMC drive holds its last current forever; the node sends
  the current frames from each command, and a watchdog timer sends zero current once the command
  is stale or motion is not allowed (`wheel_watchdog_frames`, within `WATCHDOG_QUIET_PERIODS`
  refresh periods); it never repeats a command in force.

The commands are made by commands.CommandFrames, the reports by diagnostics.BridgeDiagnostics,
both mixins of BridgeCore; the types it takes and gives are in snapshots.

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
from typing import Callable

import can

from krang_can_bridge.arm_fault import ArmFaults
from krang_can_bridge.commands import CommandFrames
from krang_can_bridge.config import CanDevicesConfig
from krang_can_bridge.diagnostics import BridgeDiagnostics
from krang_can_bridge.imu_filter import ImuPitchEstimator, PitchEstimate
from krang_can_bridge.protocols import ProtocolError, load_dbc
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols import powercube as pc
from krang_can_bridge.protocols.dmu_imu import DmuAccelerations, DmuCodec, DmuRates
from krang_can_bridge.snapshots import (
    IMU_SAMPLE,
    WHEEL_SAMPLE,
    WHEEL_SAMPLE_KINDS,
    BusFrame,
    Counters,
    Device,
    ImuSnapshot,
    JointStateSnapshot,
    ModuleState,
    WheelState,
)

logger = logging.getLogger('krang_can_bridge')

NMT_ID = 0x000
NMT_BOOT_UP, NMT_OPERATIONAL = 0x00, 0x05  # DS301 NMT state byte of 0x700 + node
NMT_STATE_NAMES = {0x04: 'STOPPED', 0x05: 'OPERATIONAL', 0x7F: 'PRE-OPERATIONAL'}
MODULE_DEVICE = 'powercube'  # the device names of the PowerCube modules: powercube/joint/bus:id
EMCY_BASE, SDO_RESPONSE_BASE, SDO_REQUEST_BASE, HEARTBEAT_BASE = 0x080, 0x580, 0x600, 0x700


class BridgeCore(CommandFrames, BridgeDiagnostics, ArmFaults):
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
        self.counters = Counters()
        self._started_at = clock()
        self._log_times: dict[str, float] = {}
        self._inhibits: dict[str, str] = {}

        w = config.wheels
        self._wheels: dict[str, WheelState] = {}
        self._wheel_by_id: dict[int, WheelState] = {}
        self._wheel_echo_ids: set[int] = set()
        self._canopen_ids: set[int] = set()
        for drive in w.drives:
            codec = amc_proto.AmcDriveCodec(drive, w, dbc)
            state = WheelState(
                codec, Device(f'amc/{drive.joint}', w.required, w.silence_timeout_s)
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
        self._nmt_state_ids = {
            HEARTBEAT_BASE + s.codec.drive.node_id: s for s in self._wheels.values()
        }
        self._wheel_echo_ids.add(amc_proto.HEARTBEAT_BASE + w.watchdog.node_id)  # our heartbeat
        self._wheel_command: tuple[float, float, float] | None = None  # (left, right, time)
        self._command_loop_at: float | None = None
        self._loop_steady_since: float | None = None
        self._wheel_sent_at: float | None = None
        self._fault = ''

        self._imu_device = Device('imu', config.imu.required, config.imu.silence_timeout_s)
        # the filter steps by the DMU's sequence counter (imu_filter.ImuPitchEstimator)
        self._imu_estimator = ImuPitchEstimator(config.imu, imu_sample_period_s)
        self._imu_rates: DmuRates | None = None
        self._imu_accel: DmuAccelerations | None = None
        self._imu_snapshot: ImuSnapshot | None = None
        self._last_stream_toggle: float | None = None
        self._imu_frame_at: float | None = None  # any DMU frame, frozen or not (stream toggle)
        self._imu_sequence: int | None = None  # of the last paired sample
        self._imu_values: tuple[float, ...] | None = None
        self._imu_same_since: float | None = None  # the values have not changed since
        self._imu_frozen = ''  # why the DMU's latest sample was dropped as frozen

        pcfg = config.powercube
        self._poll_frames: list[BusFrame] | None = None
        self._modules: dict[tuple[str, int], ModuleState] = {}
        self._arm_fault_modules: dict[tuple[str, int], str] = {}  # ArmFaults: key -> joint
        for joint in pcfg.joints:
            for m in joint.modules:
                dev = Device(
                    f'{MODULE_DEVICE}/{joint.joint}/{m.bus}:{m.module_id}',
                    pcfg.required,
                    pcfg.silence_timeout_s,
                )
                self._modules[(m.bus, m.module_id)] = ModuleState(joint, m, dev)

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
    def devices(self) -> list[Device]:
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
            elif (
                bus == self.config.wheels.bus
                and aid in self._nmt_state_ids
                and not msg.is_remote_frame
            ):
                c.canopen += 1
                self._on_nmt_state(self._nmt_state_ids[aid], msg)
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

    def _on_wheel(self, state: WheelState, msg: can.Message, now: float) -> str | None:
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

    def _on_emcy(self, state: WheelState, msg: can.Message) -> None:
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

    def _on_nmt_state(self, state: WheelState, msg: can.Message) -> None:
        """A drive's NMT state frame (DS301 0x700 + node: boot-up, heartbeat or guarding reply).
        A boot-up means the drive power-cycled or reset: its object dictionary is back to the
        defaults (no TPDO timer, no heartbeat consumer, abort option 1) and it is PRE-OPERATIONAL.
        Once started, that, or any NMT state but OPERATIONAL, latches a drive fault: only a rerun
        of its whole start-up (the recover service) makes it a drive the bridge may command."""
        data = bytes(msg.data)
        if not data:
            return
        code, joint = data[0] & 0x7F, state.codec.drive.joint
        if code == NMT_BOOT_UP:
            state.boots += 1
            logger.warning(f'{joint}: boot-up message (drive power-cycled or reset)')
            if state.started:
                self._latch_fault(
                    f'{joint}: drive rebooted (DS301 boot-up): its settings and watchdog are '
                    'back to the defaults'
                )
            state.started = state.armed = False
        elif code != NMT_OPERATIONAL and state.started:
            name = NMT_STATE_NAMES.get(code, f'0x{code:02X}')
            self._latch_fault(f'{joint}: drive left NMT OPERATIONAL for {name}')
            state.started = state.armed = False

    def _check_drive_state(self, state: WheelState) -> None:
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
        self._imu_frame_at = now
        if isinstance(sample, DmuRates):
            self._imu_rates = sample
        else:
            self._imu_accel = sample
        r, a = self._imu_rates, self._imu_accel
        if r is None or a is None or r.sequence != a.sequence:
            return None
        self._imu_rates = self._imu_accel = None  # one filter update per paired sample
        if not self._imu_alive(r, a, now):
            return None
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

    def _imu_alive(self, r: DmuRates, a: DmuAccelerations, now: float) -> bool:
        """Whether a paired DMU sample is a live one (then the DMU counts as heard from). A
        frozen DMU keeps sending at its rate: a sequence counter that did not advance, or (with
        imu.frozen_after_s) values bit-identical for longer than that, which the sensor's noise
        does not allow. Its samples are dropped (no filter step, no /imu/data), so the DMU falls
        silent after its silence timeout. A repeated value within frozen_after_s is used but is
        no sign of life either."""
        values = (r.x, r.y, r.z, a.x, a.y, a.z)
        frozen_after = self.config.imu.frozen_after_s
        repeated = frozen_after > 0 and values == self._imu_values
        stuck = r.sequence == self._imu_sequence
        if not repeated:
            self._imu_same_since = now
        self._imu_sequence, self._imu_values = r.sequence, values
        reason = ''
        if stuck:
            reason = f'sequence counter stuck at {r.sequence}'
        elif repeated and now - self._imu_same_since > frozen_after:
            reason = f'values bit-identical for {now - self._imu_same_since:.3f} s'
        if reason:
            c = self.counters
            c.frozen_samples += 1
            c.last_frozen = reason
            if not self._imu_frozen:
                logger.error(f'DMU frozen ({reason}): its samples are dropped')
            self._imu_frozen = reason
            return False
        if self._imu_frozen:
            logger.warning(f'DMU live again after it froze ({self._imu_frozen})')
            self._imu_frozen = ''
        if not repeated:
            self._imu_device.last_seen = now
        return True

    @property
    def imu_frozen(self) -> str:
        """Why the DMU's latest sample was dropped as frozen; '' while it is live."""
        return self._imu_frozen

    def _on_module(self, state: ModuleState, msg: can.Message, now: float) -> None:
        try:
            reply = pc.decode_reply(msg)
        except ProtocolError:
            state.device.malformed += 1
            raise
        if reply.command == pc.GET_PARAM and reply.selector == pc.ACT_FPOS:
            state.position, state.position_at = float(reply.value), now
        elif reply.command == pc.GET_PARAM and reply.selector == pc.ACT_FVEL:
            state.velocity = float(reply.value)
        elif reply.command == pc.SET_MOTION:
            state.position, state.position_at = float(reply.value), now
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

    @property
    def inhibits(self) -> dict[str, str]:
        """The reasons set by `inhibit`, by key."""
        return dict(self._inhibits)

    def _silence_stops(self, device: Device, now: float) -> bool:
        """Whether `device` is required and silent; a PowerCube module heard from and then silent
        is an arm fault instead (arm_fault), which does not stop the wheels."""
        if not (device.required and device.silent(now)):
            return False
        return device.last_seen is None or not device.name.startswith(f'{MODULE_DEVICE}/')

    def motion_allowed(self, now: float | None = None) -> bool:
        now = self._now(now)
        if self._fault or self._inhibits:
            return False
        if any(self._silence_stops(d, now) for d in self.devices):
            return False
        if self.config.imu.required and (
            self._imu_snapshot is None or not self._imu_snapshot.ready
        ):
            return False
        return True

    # ---- state ----------------------------------------------------------------------------------
    # A silent wheel drive's last reading is left out of the state, not republished under a fresh
    # stamp: the controller then sees its input go stale and stops (its own stale_timeout_s), as
    # the bridge does. A silent PowerCube module is an arm fault instead: its joint is held by the
    # module, so it stays at its last position with velocity 0 and the controller balances on.
    def joint_state(self, now: float | None = None) -> JointStateSnapshot:
        """Body joints whose modules have all been heard from (a silent one at its last position,
        velocity 0: see arm_fault), wheels heard from within their silence timeout.

        A module speaks only when polled, so its reading is up to a poll period old: a moving
        joint is reported where its polled velocity has taken it since (at most one poll period
        ahead). A joint read 20 ms ago at 0.35 rad/s is 7 mrad further on, and a balance pitch
        paired with the older joints is off by its own rate times that age (docs/can.md)."""
        now = self._now(now)
        self._check_modules(now)
        horizon = 1.0 / self.config.powercube.poll_rate_hz
        names, pos, vel, eff = [], [], [], []
        for joint in self.config.powercube.joints:
            states = [self._modules[(m.bus, m.module_id)] for m in joint.modules]
            if any(s.position is None for s in states):
                continue
            speeds = [0.0 if s.device.silent(now) else s.velocity for s in states]
            names.append(joint.joint)
            pos.append(
                sum(
                    s.module.sign * _extrapolated(s, v, now, horizon)
                    for s, v in zip(states, speeds)
                )
                / len(states)
            )
            vel.append(
                sum(s.module.sign * v for s, v in zip(states, speeds)) / len(states)
                if all(v is not None for v in speeds)
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

    def wheel_state(self, joint: str) -> WheelState:
        return self._wheels[joint]

    def imu_state(self, now: float | None = None) -> ImuSnapshot | None:
        """The filtered IMU, or None while the DMU is silent."""
        return None if self._imu_device.silent(self._now(now)) else self._imu_snapshot


def _extrapolated(state, speed, now: float, horizon: float) -> float:
    """A module's position now from its last reading and polled speed (module coordinates)."""
    if not speed or state.position_at is None:
        return state.position
    return state.position + speed * min(max(now - state.position_at, 0.0), horizon)
