"""The CAN bridge at run time, without ROS: BridgeCore driven by the buses, a clock and the drives'
start-up, with the samples handed to a `publish` callable.

`BridgeRuntime` owns what happens between the buses and the topics:
- the time base (sample_clock.TimeBase): the devices' time, wall or the simulator's;
- the receive path (`on_received`): each frame to the core under one lock, each completed sample
  out at once, a wheel sample held for the next DMU sample while the DMU streams (below), zero
  current at once when a frame latches a drive fault, the SDO responses to canopen;
- the sends: wheel currents from each command and from the watchdog timer, PowerCube polls and
  moves through a send thread, the drives' watchdog frames from their own thread; frames a bus
  refuses, counted, and a wheels' bus refusing them all for the command timeout stops motion;
- the drives' start-up once the command loop runs steadily (`start_drive`: one verified run of one
  drive's sequence; `bring_up_drive`: that until it is done) and the recovery from a latched
  drive fault or arm fault (`recover`), both in threads because SDO transfers block;
- the diagnostics of all this.

Held sample: the drives' TPDOs come at any phase of the DMU's period (free-running clocks), so a
/joint_states published as it completed fell between a sample and its command at most phases.
While the DMU streams, a wheel sample waits for the next DMU sample and goes out just before its
/imu/data (a newer wheel sample replaces a waiting one; its message is built as it completes, so
the DMU sample pays only its publication). Once no DMU sample has come for 1.5 of its intervals
(or the DMU runs slower than 1 / IMU_HOLD_MAX_S), wheel samples go out as they complete.

The ROS node (krang_can_bridge.node) only wires this to topics, services, timers and parameters.
Over 600 lines: these are one job, the bridge's threads around the core, sharing its lock.
"""

from __future__ import annotations

import functools
import logging
import math
import threading
import time
from typing import Any, Callable, NamedTuple

import can
import canopen

from krang_can_bridge.bridge import BridgeCore
from krang_can_bridge.bus_io import BusReader, SendFailures, SendThread
from krang_can_bridge.config import CanDevicesConfig, WheelDriveConfig
from krang_can_bridge.imu_filter import pitch_axis, tilt_direction
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols import amc_canopen
from krang_can_bridge.sample_clock import SampleClock, TimeBase
from krang_can_bridge.snapshots import (
    ERROR,
    IMU_SAMPLE,
    OK,
    WARN,
    WHEEL_SAMPLE,
    BusFrame,
    DiagnosticReport,
    ImuSnapshot,
    JointStateSnapshot,
)
from krang_core import names
from krang_core.log import Throttled

logger = logging.getLogger('krang_can_bridge')

IMU_HOLD_MAX_S = 0.05  # a DMU slower than 20 Hz holds no wheel sample back
IMU_CLOCK_LAG_MAX_S = 0.04  # counter-timed DMU samples: within this of the clock (< its timeout)
STARTUP_WARN_PERIOD_S = 10.0  # a failing start-up warns at most this often per drive
STARTUP_SETTLE_S = 1.0  # the command loop runs steadily this long before the drives start
STARTUP_SETTLE_MAX_S = 10.0  # ... or the drives start anyway after this long


def imu_vectors(imu: ImuSnapshot, mount_angle_rad: float):
    """(angular velocity, linear acceleration) of /imu/data from a DMU sample: its rates and
    specific force turned by the mount angle into x forward, y left, z up (at zero pitch); the
    pitch rate is the filtered one."""
    e, d = _sensor_axes(mount_angle_rad)
    w, f = imu.rates, imu.specific_force
    return (-_dot(d, w), imu.pitch_rate, w[2]), (-_dot(d, f), _dot(e, f), f[2])


@functools.lru_cache(maxsize=4)
def _sensor_axes(mount_angle_rad: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The pitch axis and the tilt direction in sensor coordinates, as floats (per sample, the
    dot products cost a tenth of numpy's on three elements)."""
    return (
        tuple(map(float, pitch_axis(mount_angle_rad))),
        tuple(map(float, tilt_direction(mount_angle_rad))),
    )


def _dot(a, b) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


class Output(NamedTuple):
    """A sample on its way out: its topic, its message and stamp (as the encoders made them) and
    its device time."""

    topic: str
    message: Any
    stamp: Any
    t: float


class BridgeRuntime:
    """BridgeCore on its buses (see the module docstring).

    `publish(topic, message)` sends a sample (from the receive thread); it returns False once the
    process is shutting down, and the frame's other samples are dropped. `stamp(seconds)` makes a
    stamp, `encode_imu(imu, stamp)` and `encode_joints(joints, stamp)` the messages.
    `run_startup(network, drive, wheels, sdo_timeout_s)` is one drive's start-up sequence
    (protocols.amc_canopen.run_startup)."""

    def __init__(
        self,
        config: CanDevicesConfig,
        buses: dict[str, can.BusABC],
        *,
        publish: Callable[[str, Any], bool],
        stamp: Callable[[float], Any],
        encode_imu: Callable[[ImuSnapshot, Any], Any],
        encode_joints: Callable[[JointStateSnapshot, Any], Any],
        time_base: TimeBase | None = None,
        publish_rate_hz: float = 0.0,
        imu_sample_period_s: float = 0.0,
        send_timeout_s: float = 0.002,
        sdo_timeout_s: float = 0.3,
        recover_timeout_s: float = 1.0,
        amc_startup: bool = True,
        run_startup=amc_canopen.run_startup,
    ):
        self.config, self.buses = config, buses
        self._publish, self._stamp = publish, stamp
        self._encode_imu, self._encode_joints = encode_imu, encode_joints
        self.time = time_base or TimeBase()
        self.core = BridgeCore(
            config, clock=self.time.device_time, imu_sample_period_s=imu_sample_period_s
        )
        # imu_sample_period_s > 0: DMU samples are timed by their sequence counter
        period = imu_sample_period_s
        self._imu_clock = (
            SampleClock(period, lag_max_s=IMU_CLOCK_LAG_MAX_S) if period > 0 else None
        )
        self.lock = threading.Lock()  # the core's: one user at a time
        self._sdo_lock = threading.Lock()  # one SDO user at a time: start-up or recover
        self._stop = threading.Event()
        self._send_timeout = send_timeout_s
        self._sdo_timeout = sdo_timeout_s
        self._recover_timeout = recover_timeout_s
        self._run_startup = run_startup
        self.amc_startup = amc_startup
        self.send_failures = SendFailures()
        self._receive_errors: dict[str, str] = {}
        self._warn_send = Throttled(logger.warning, 1.0)
        self._warn_startup = {
            d.joint: Throttled(logger.warning, STARTUP_WARN_PERIOD_S) for d in config.wheels.drives
        }
        self._published_fault: str | None = None
        self._published_arm_fault: tuple[str, list[str]] | None = None
        self._joint_period = 1.0 / publish_rate_hz if publish_rate_hz > 0 else 0.0
        self._joints_published_at = -math.inf
        self._imu_at, self._imu_interval = -math.inf, math.inf  # arrivals of /imu/data samples
        self._held_joints: Output | None = None  # waiting for the next /imu/data
        self.published = {names.IMU: 0, names.JOINT_STATES: 0}
        self.network = canopen.Network(buses[config.wheels.bus])
        self._startup_status: dict[str, str] = {}
        for drive in config.wheels.drives:
            self._startup_status[drive.joint] = 'pending'
            if amc_startup:
                self.core.inhibit(_startup_key(drive), f'{drive.joint}: AMC start-up not done')
        self.reader = self.sender = None
        self._verify_startup = True
        self.startup_thread = threading.Thread(target=self._startup_worker, daemon=True)
        self.watchdog_thread = threading.Thread(target=self._watchdog_worker, daemon=True)
        self._beat_at = -math.inf  # monotonic time of the last watchdog frames sent in full

    # ---- threads ------------------------------------------------------------------------------
    def start(self, retry_s: float, pump=None, on_frame=None) -> None:
        """Start reading the buses (the DMU's first: it is read first when several have frames
        waiting), the send thread, the start-up and the watchdog. `pump` (a bus_io.Pump): composed
        in one process, frames handed over by the composition and sent in line, so the run is the
        same every time. `on_frame` replaces on_received as the reader's callback."""
        imu_first = dict(sorted(self.buses.items(), key=lambda b: b[0] != self.config.imu.bus))
        self.reader = (pump.reader if pump else BusReader)(
            imu_first, on_frame or self.on_received, self.on_bus_error
        )
        self.sender = None if pump else SendThread(self.send, self.on_send_error)
        # composed, the devices are emulators that the composition steps once the drives are
        # enabled, in the one process: no statusword comes before, and no other process stalls
        # the command loop (start_drive, _wait_for_a_steady_loop)
        self._verify_startup = pump is None
        self._retry_s = retry_s
        self.startup_thread.start()
        self.watchdog_thread.start()

    def close(self) -> None:
        """Zero the wheel currents, stop the threads, release the buses."""
        self._stop.set()
        try:
            with self.lock:
                frames = self.core.wheel_current_frames(0.0, 0.0, self.time.device_time())
            self.send(frames)
        except Exception:  # noqa: BLE001 - best effort on the way out
            pass
        if self.reader is not None:
            self.reader.stop()
        if self.sender is not None:
            self.sender.stop()
        for bus in self.buses.values():
            bus.shutdown()

    # ---- receive --------------------------------------------------------------------------------
    def on_received(self, bus: str, msg: can.Message) -> Output | None:
        """One frame: to the core, its samples out; returns the /imu/data sample it published, if
        any."""
        if self._stop.is_set():  # closing: the drives' reaction to our silence is expected
            return None
        if not self.time.known():  # simulation, before its clock: no time to put the frame at
            self._notify_sdo(bus, msg)  # an SDO answer needs none (the start-up's transfers)
            return None
        with self.lock:
            now = arrived = self.time.frame_time()
            self.time.frame_seen(now)
            if (
                self._imu_clock
                and bus == self.config.imu.bus
                and msg.arbitration_id in self.core.dmu.feedback_ids
            ):
                now = self._imu_sample_time(msg, now)
            fault = self.core.fault_reason
            sample = self.core.on_frame(msg, now, bus)
            out = held = None
            if sample == IMU_SAMPLE:
                out = self._imu_out(now)
                if out is not None:
                    self._imu_interval, self._imu_at = arrived - self._imu_at, arrived
                    held, self._held_joints = self._released(self._held_joints), None
            elif sample == WHEEL_SAMPLE:
                joints = self._joints_out(now)
                if not self._imu_due(arrived):  # out now; so is one held for a silent DMU
                    out, self._held_joints = self._released(joints or self._held_joints), None
                elif joints is not None:  # out just before the next /imu/data
                    self._held_joints = joints
            # a drive fault this frame latched: zero current at once, not at the next command
            stop = (
                self.core.wheel_current_frames(0.0, 0.0, self.time.device_time())
                if self.core.fault_reason and not fault
                else []
            )
        self.send(stop)
        for sample_out in (held, out):
            if sample_out is None:
                continue
            if not self._publish(sample_out.topic, sample_out.message):
                return None  # shutting down under this thread; close() follows
            self.published[sample_out.topic] += 1
        self._notify_sdo(bus, msg)
        return out if out is not None and out.topic == names.IMU else None

    def _notify_sdo(self, bus: str, msg: can.Message) -> None:
        """An SDO response, to the start-up's transfers (canopen's network)."""
        if (
            bus == self.config.wheels.bus
            and not msg.is_error_frame
            and msg.arbitration_id in self.network.subscribers
        ):
            self.network.notify(msg.arbitration_id, msg.data, msg.timestamp)

    def _imu_due(self, now: float) -> bool:
        """Whether the DMU streams: its last sample came less than 1.5 of its intervals before
        `now` (arrival times), so a wheel sample waits for the next one."""
        interval = self._imu_interval
        return interval <= IMU_HOLD_MAX_S and now - self._imu_at < 1.5 * interval

    def _imu_out(self, now: float) -> Output | None:
        """The DMU sample a frame completed at `now`, or None while the filter has no estimate;
        called under the lock."""
        imu = self.core.imu_state(now)
        if imu is None:
            return None
        stamp = self._stamp(self.time.stamp_seconds(imu.stamp))
        return Output(names.IMU, self._encode_imu(imu, stamp), stamp, now)

    def _joints_out(self, now: float) -> Output | None:
        """The wheel sample completed at `now`; None beyond publish_rate_hz (counted from the last
        one released) or with no joint known."""
        if now - self._joints_published_at < 0.999 * self._joint_period:
            return None
        joints = self.core.joint_state(now)
        if not joints.names:
            return None
        stamp = self._stamp(self.time.stamp_seconds(now))
        return Output(names.JOINT_STATES, self._encode_joints(joints, stamp), stamp, now)

    def _released(self, joints: Output | None) -> Output | None:
        """`joints` on its way out: the publish rate counts from it."""
        if joints is not None:
            self._joints_published_at = joints.t
        return joints

    def _imu_sample_time(self, msg: can.Message, now: float) -> float:
        """Time of a DMU frame from its sequence counter; `now` if undecodable."""
        try:
            seq = self.core.dmu.decode(msg).sequence
        except Exception:  # noqa: BLE001 - the core counts the malformed frame
            return now
        return self._imu_clock.time_of(seq, now)

    def on_bus_error(self, bus: str, exc: Exception) -> None:
        self._receive_errors[bus] = f'{type(exc).__name__}: {exc}'
        logger.error(f'CAN receive on {bus} stopped: {exc}')

    # ---- send -----------------------------------------------------------------------------------
    def send(self, frames: list[BusFrame]) -> bool:
        """Send each frame (True when every one went out); a refused one (a full transmit
        queue, a bus-off controller) is counted and its run of failures timed
        (bus_io.SendFailures). Once every send on the wheels' bus has failed for
        wheels.command_timeout_s, motion is inhibited (zero current is then what the bridge tries
        to send; the drives' watchdog stops them anyway once the beat has not gone out for its
        timeout); the first frame that goes out again lifts it."""
        all_sent = True
        for bus, msg in frames:
            try:
                self.buses[bus].send(msg, timeout=self._send_timeout)
            except can.CanError as exc:
                all_sent = False
                error = f'{type(exc).__name__}: {exc}'
                failing_for = self.send_failures.failed(bus, error, time.monotonic())
                self._warn_send(f'send on {bus} failed: {error}')
                if bus == self.config.wheels.bus and (
                    failing_for > self.config.wheels.command_timeout_s
                ):
                    self._inhibit_sends(
                        bus, f'wheel frames refused by {bus} for {failing_for:.3f} s ({error})'
                    )
            else:
                ended = self.send_failures.sent(bus, time.monotonic())
                if ended is not None:
                    logger.warning(f'send on {bus} works again after {ended:.3f} s of failures')
                    if bus == self.config.wheels.bus:
                        self._inhibit_sends(bus, None)
        return all_sent

    def _inhibit_sends(self, bus: str, reason: str | None) -> None:
        with self.lock:
            self.core.inhibit(f'send/{bus}', reason)

    def send_later(self, frames: list[BusFrame], key=None) -> None:
        """Frames no control loop waits for: sent by the send thread, a newer batch of the same
        `key` replacing one still waiting (see bus_io.SendThread)."""
        if self.sender is None:
            self.send(frames)
        else:
            self.sender.put(frames, key)

    def on_send_error(self, exc: Exception) -> None:
        if not self._stop.is_set():
            logger.error(f'CAN send thread: {type(exc).__name__}: {exc}')

    def wheel_effort(self, efforts) -> None:
        """A wheel command (efforts by wheel, None when malformed: zero current on both): its
        current frames go out at once."""
        with self.lock:
            self.core.set_wheel_effort_command(efforts, self.time.device_time())
            frames = self.core.wheel_command_frames(self.time.device_time())
        self.send(frames)

    def joint_positions(self, targets: dict[str, float]) -> None:
        """Joint targets by name; a newer target for the same modules replaces one not yet
        sent."""
        with self.lock:
            frames = self.core.joint_position_frames(targets, self.time.device_time())
        self.send_later(frames, ('move', *sorted({(f.bus, f.msg.arbitration_id) for f in frames})))

    def send_wheel_commands(self) -> None:
        with self.lock:
            frames = self.core.wheel_command_frames(self.time.device_time())
        self.send(frames)

    def wheel_watchdog(self) -> None:
        """Zero current once commands stop or motion is not allowed; never a command in force."""
        with self.lock:
            frames = self.core.wheel_watchdog_frames(self.time.device_time())
        self.send(frames)

    def poll_modules(self) -> None:
        with self.lock:
            frames = self.core.poll_frames()
        self.send_later(frames, 'poll')

    def check_imu_stream(self) -> None:
        with self.lock:
            frames = self.core.imu_stream_frames(self.time.device_time())
        if frames:
            logger.info('DMU silent: sending the stream toggle')
        self.send(frames)

    def _watchdog_worker(self) -> None:
        """Send the drives' watchdog frames every period; the core withholds them when the wheel
        command loop is quiet, and a hung core (lock held) stops them too."""
        period = self.config.wheels.watchdog.period_s
        if self.config.wheels.watchdog.mechanism == 'none':
            return
        due = time.monotonic()
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            due = max(due + period, time.monotonic())
            with self.lock:
                frames = self.core.watchdog_frames(self.time.device_time())
            if frames and self.send(frames):
                self._beat_at = time.monotonic()

    def await_beat(self) -> None:
        """Block until a watchdog frame has gone out after this call (a start-up step: the drive's
        heartbeat consumer, just configured, watches only from the first beat it receives);
        StartupNotVerified if none does within recover_timeout_s. Not when no watchdog thread
        runs (composed, or a runtime not started)."""
        if not (self._verify_startup and self.watchdog_thread.is_alive()):
            return
        asked = time.monotonic()
        deadline = asked + self._recover_timeout
        while self._beat_at <= asked:
            if time.monotonic() > deadline or self._stop.is_set():
                raise StartupNotVerified(
                    f'no watchdog frame went out within {self._recover_timeout} s of configuring '
                    'the drive watchdog: the drive is not enabled'
                )
            time.sleep(0.002)

    # ---- drive start-up and recovery ------------------------------------------------------------
    def start_drive(self, drive: WheelDriveConfig) -> list[str]:
        """One run of a drive's start-up sequence (fault reset, the watchdog objects read back,
        enable): its mismatches with the config (the drive then left disabled). The drive counts
        as started only without them, with no boot-up during the run and its statusword TPDO
        reporting OPERATION_ENABLED after it (not awaited composed); StartupNotVerified
        otherwise. Raises what the SDO transfers raise."""
        with self.lock:
            self.core.drive_started(drive.joint, False)
            boots = self.core.wheel_state(drive.joint).boots
        with self._sdo_lock:
            mismatches = self._run_startup(
                self.network, drive, self.config.wheels, self._sdo_timeout, armed=self.await_beat
            )
        if not mismatches and self._verify_startup:
            self._verify_enabled(drive.joint, boots)
        with self.lock:
            self.core.drive_started(drive.joint, not mismatches)
        return mismatches

    def _verify_enabled(self, joint: str, boots: int) -> None:
        """Wait up to recover_timeout_s for a statusword TPDO saying OPERATION_ENABLED."""
        since = self.time.frame_time()
        deadline = time.monotonic() + self._recover_timeout
        while True:
            with self.lock:
                state = self.core.wheel_state(joint)
                rebooted = state.boots != boots
                seen = state.drive_status_at is not None and state.drive_status_at >= since
                name = amc_proto.drive_state(state.drive_status) if seen else None
            if rebooted:
                raise StartupNotVerified(f'{joint} rebooted during its start-up')
            if name == 'OPERATION_ENABLED':
                return
            if name == 'FAULT' or time.monotonic() > deadline or self._stop.is_set():
                raise StartupNotVerified(
                    f'{joint} {"still " if name == "FAULT" else ""}reports {name} (statusword '
                    f'0x{state.drive_status:04X}) after its start-up'
                    if seen
                    else f'{joint}: no statusword within {self._recover_timeout} s of its start-up'
                )
            time.sleep(0.005)

    def bring_up_drive(self, drive: WheelDriveConfig, retry_s: float) -> None:
        """start_drive until it runs through (retrying a failed transfer every `retry_s`); then
        motion is allowed by this drive, or inhibited with the mismatches."""
        key = _startup_key(drive)
        while not self._stop.is_set():
            try:
                mismatches = self.start_drive(drive)
            except Exception as exc:  # noqa: BLE001 - SDO timeout/abort or bus error: retry
                self._startup_status[drive.joint] = f'failed: {type(exc).__name__}: {exc}'
                self._warn_startup[drive.joint](f'{drive.joint} start-up failed ({exc}); retrying')
                self._stop.wait(retry_s)
                continue
            with self.lock:
                if mismatches:
                    status = 'constants mismatch: ' + '; '.join(mismatches)
                    self._startup_status[drive.joint] = status
                    self.core.inhibit(key, '; '.join(mismatches))
                    logger.error(status)
                else:
                    self._startup_status[drive.joint] = 'enabled'
                    self.core.inhibit(key, None)
            return

    def _startup_worker(self) -> None:
        with self.lock:
            frames = self.core.startup_frames()
        self.send(frames)
        if not self.amc_startup:
            return
        self._wait_for_a_steady_loop()
        for drive in self.config.wheels.drives:
            self.bring_up_drive(drive, self._retry_s)

    def _wait_for_a_steady_loop(self) -> None:
        """Arm the drives' watchdog once the wheel command loop has run steadily for
        STARTUP_SETTLE_S (device time), or after STARTUP_SETTLE_MAX_S (wall time): a process
        stalls most in its first second, and a beat withheld then trips a drive just enabled,
        a fault only a recover clears (docs/can.md). Not when composed (start: `pump`)."""
        if self.config.wheels.watchdog.mechanism == 'none' or not self._verify_startup:
            return
        deadline = time.monotonic() + STARTUP_SETTLE_MAX_S
        while not self._stop.is_set() and time.monotonic() < deadline:
            with self.lock:
                steady = self.core.loop_steady_for(self.time.device_time())
            if steady >= STARTUP_SETTLE_S:
                return
            self._stop.wait(0.02)
        if not self._stop.is_set():
            logger.warning(
                f'wheel command loop not steady for {STARTUP_SETTLE_S} s within '
                f'{STARTUP_SETTLE_MAX_S} s: starting the drives anyway'
            )

    @property
    def startup_status(self) -> dict[str, str]:
        """Each drive's start-up: 'pending', 'enabled', 'failed: ...' or 'constants mismatch'."""
        return dict(self._startup_status)

    def fault_changed(self) -> str | None:
        """The latched drive fault's reason ('' when clear) if it changed since the last call (the
        first call always returns it), else None."""
        with self.lock:
            reason = self.core.fault_reason
        if reason == self._published_fault:
            return None
        self._published_fault = reason
        return reason

    def arm_fault_changed(self) -> tuple[str, list[str]] | None:
        """The arm fault's (reason, joints) (('', []) when clear) if it changed since the last
        call (the first call always returns it), else None."""
        with self.lock:
            fault = self.core.arm_fault(self.time.device_time())
        if fault == self._published_arm_fault:
            return None
        self._published_arm_fault = fault
        return fault

    def recover(self) -> tuple[bool, str]:
        """The drives' recovery (`recover_drives`), then the arm's: once every PowerCube module
        answers, the modules named in the arm fault get their start-up frames again and the
        fault is cleared; refused with the reason otherwise."""
        ok, text = self.recover_drives()
        with self.lock:
            reason, _ = self.core.arm_fault(self.time.device_time())
            answering, why = self.core.arm_recover_status(self.time.device_time())
            frames = self.core.arm_fault_startup_frames() if answering else []
        if not ok or not reason:
            return ok, text
        if not answering:
            return False, f'{text}; refused: {why}; arm fault still latched: {reason}'
        self.send(frames)
        with self.lock:
            self.core.clear_arm_fault()
        return True, f'{text}; arm recovered from: {reason}'

    def recover_drives(self) -> tuple[bool, str]:
        """Every drive's start-up sequence again (DS402 fault reset and enable), then unlatch if
        all report OPERATION_ENABLED (BridgeCore.recover_status); refused with the reason
        otherwise."""
        with self.lock:
            reason = self.core.fault_reason
        if not reason:
            return True, 'no drive fault latched'
        for drive in self.config.wheels.drives:
            try:
                mismatches = self.start_drive(drive)
            except Exception as exc:  # noqa: BLE001 - SDO timeout/abort or bus error
                return False, (
                    f'{drive.joint}: fault reset and enable failed '
                    f'({type(exc).__name__}: {exc}); fault still latched: {reason}'
                )
            if mismatches:
                return False, '; '.join(mismatches)
        since = self.time.frame_time()
        deadline = time.monotonic() + self._recover_timeout
        while True:
            with self.lock:
                ok, why = self.core.recover_status(since)
                if ok:
                    self.core.clear_fault()
                    return True, f'recovered from: {reason}'
            if ok is False or time.monotonic() > deadline:
                return False, f'refused: {why}; fault still latched: {reason}'
            time.sleep(0.01)

    def recover_keeping_alive(self) -> tuple[bool, str]:
        """recover() in a thread while this one keeps the wheel command loop going (zero current
        while latched), so the drives' watchdog goes on seeing a live bridge."""
        result = []
        worker = threading.Thread(target=lambda: result.append(self.recover()), daemon=True)
        worker.start()
        period = 1.0 / self.config.wheels.command_rate_hz
        while worker.is_alive():
            self.send_wheel_commands()
            worker.join(period)
        return result[0] if result else (False, 'recover failed')

    # ---- diagnostics ----------------------------------------------------------------------------
    def diagnostics(self) -> list[DiagnosticReport]:
        """The core's reports, then the buses' I/O errors, the samples published and each drive's
        start-up."""
        with self.lock:
            reports = self.core.diagnostics(self.time.device_time())
        stop_after = self.config.wheels.command_timeout_s
        failing = {
            b: f
            for b, f in self.send_failures.failing(time.monotonic()).items()
            if f[0] > stop_after
        }
        for bus in self.buses:
            sent_err = self.send_failures.counts.get(bus, 0)
            recv_err = self._receive_errors.get(bus)
            if sent_err or recv_err:
                text = recv_err or f'{sent_err} send errors'
                if bus in failing:
                    text += f'; every send failing for {failing[bus][0]:.1f} s: {failing[bus][1]}'
                reports.append(
                    DiagnosticReport(
                        f'can_bridge: bus {bus} I/O',
                        ERROR if recv_err or bus in failing else WARN,
                        text,
                        {'send_errors': sent_err, 'receive_error': recv_err},
                    )
                )
        reports.append(
            DiagnosticReport(
                'can_bridge: samples published',
                OK,
                ', '.join(f'{n} {topic}' for topic, n in self.published.items()),
                {topic: str(n) for topic, n in self.published.items()},
            )
        )
        for joint, status in self._startup_status.items():
            reports.append(
                DiagnosticReport(
                    f'can_bridge: amc/{joint} start-up',
                    OK if status == 'enabled' else WARN,
                    status,
                    {},
                )
            )
        return reports


class StartupNotVerified(RuntimeError):
    """A drive's start-up sequence ran but the drive is not verifiably enabled by it."""


def _startup_key(drive: WheelDriveConfig) -> str:
    return f'startup/{drive.joint}'
