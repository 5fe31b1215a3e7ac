"""can_bridge: the thin rclpy shell around krang_can_bridge.bridge.BridgeCore.

Buses come from the device map (parameter `devices_file`, default the robot's SocketCAN map
config/can_devices_robot.yaml; a bare file name is looked up in config/, so the simulated node set
passes `can_devices.yaml` in config/sim_params.yaml). A bus that cannot be opened ends the node
with one line naming the interface (and, for SocketCAN, the `ip link` command) and exit code 1.
One receive thread (bus_io.BusReader) feeds the frames of every bus to the core (under a lock),
so the executor never blocks on CAN; the kernel passes it only the ids the core reads
(BridgeCore.received_ids, bus_io.receive_only), and each socket's receive queue is enlarged
(bus_io.enlarge_receive_buffer) so that a stall of the thread delays frames instead of losing
them. The node is event-driven: the receive thread publishes each sample as soon as the core
says its frames are in (rclpy publishers may be called from any thread; the message is published
outside the lock), and the wheel current frames go out from the command callback. The control
path's messages (/imu/data, /joint_states, the wheel command) are written and read as their
serialized bytes (krang_ros.wire). The PowerCube polls and moves go out from a send thread
(bus_io.SendThread), so that the executor is free for the next command while they are sent. The
AMC start-up and the recovery (blocking SDO transfers through canopen) run in their own threads,
and so does the drive-side watchdog's heartbeat, which the core withholds when the wheel command
loop (the executor) stops running (docs/can.md).

Topics:
- publishes /joint_states (sensor_msgs/JointState: body joints + JLWheel/JRWheel, URDF names; only
  joints with data; effort: the wheels' measured currents as torque at the wheel [N m], NaN for the
  body joints) for each complete wheel sample (position, velocity and current TPDOs of both
  drives), at most at publish_rate_hz, stamped with the sample's time; /imu/data (sensor_msgs/Imu,
  sensor-data QoS) on each DMU sample (rates and accelerations of one sequence number), stamped
  with the sample's time; /diagnostics (1 Hz). While the DMU streams, a wheel sample waits for
  the next DMU sample and goes out just before its /imu/data (a newer wheel sample replaces a
  waiting one; its message is built as it completes, so the DMU sample pays only its
  publication): the drives' TPDOs come at any phase of the DMU's period (free-running clocks),
  and a /joint_states published as they completed fell between a sample and its command (one
  process, one GIL) at most phases. The controller's step on a sample then also has the newest
  wheel sample before it, never one newer than the sample. Once no DMU sample has come for 1.5
  of its intervals (or the DMU runs slower than 20 Hz), wheel samples go out as they complete.
  The DMU's bus is read first when several have frames waiting (ahead of the PowerCube nets;
  the drives share it on Krang);
- subscribes /wheel_effort_cmd (sensor_msgs/JointState: name [JLWheel, JRWheel], effort N m at the
  wheel, header.stamp = the /imu/data sample it answers; reliable) and /joint_position_cmd
  (sensor_msgs/JointState, positions by name);
- publishes /can_bridge/drive_fault (std_msgs/String, latched): the latched drive fault's reason,
  '' when clear (BridgeCore: a FAULT or EMCY of any drive stops both wheels; the frame that latches
  it sends zero current at once);
- serves ~/recover (std_srvs/Trigger, /can_bridge/recover): DS402 fault reset and the enable
  sequence (the start-up again), then unlatches only if every drive reports OPERATION_ENABLED;
  refused with the reason otherwise.

/imu/data: orientation = rotation by q_base (hardware IMU pitch, positive = top tilting forward)
about +y, the axle pointing left; angular_velocity.y = the filtered pitch rate; the other
components and linear_acceleration (specific force, m/s^2) are the bias-corrected DMU readings
turned by the mount angle into x forward, y left, z up (at zero pitch). Roll and yaw are not
observed: their orientation variances are set to 1e6.

Wheel currents go out from each command; a watchdog timer at wheels.command_rate_hz sends zero
current once commands stop or motion is not allowed, and never repeats a command in force
(BridgeCore.wheel_watchdog_frames). Each command restarts that timer, so its callback never runs
while commands flow (rcl's reset still wakes the executor once, with nothing to run; letting the
timer fire instead measured the same). A command older than
wheels.command_timeout_s, a malformed one, a silent device, or an AMC start-up not (yet) done or
whose drive constants disagree with the config gives zero current (see BridgeCore).

Parameters: BridgeParams below (`can_bridge --help`), read once at start. With use_sim_time every
time of the core (IMU filter steps, silence and command timeouts) is the simulator's /clock, not
wall time.
"""

from __future__ import annotations

import functools
import logging
import math
import sys
import threading
import time
from dataclasses import dataclass, field

import can
import canopen
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from krang_can_bridge.bridge import IMU_SAMPLE, WHEEL_SAMPLE, BridgeCore, BusFrame
from krang_can_bridge.bus_io import BusReader, SendThread, enlarge_receive_buffer, receive_only
from krang_can_bridge.config import (
    BusConfig,
    ConfigError,
    load_devices,
    resolve_devices_file,
    robot_devices_file,
)
from krang_can_bridge.imu_filter import pitch_axis, tilt_direction
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.sample_clock import SampleClock
from krang_ros import messages, names, params, realtime, topics, trace, wire
from krang_ros.log import Throttled
from krang_ros.spin import run_node

SIM_TIME_SLACK_S = 0.025  # with use_sim_time: checks run at most this far past the newest frame
HARDWARE_ID = 'krang_can'
CAN_BITRATE = 1000000  # every Krang net runs at 1 Mbit/s (docs/can.md)


def _doc(text: str) -> dict:
    return {'doc': text}


@functools.lru_cache(maxsize=4)
def _sensor_axes(mount_angle_rad: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The pitch axis and the tilt direction in sensor coordinates, as floats (per sample, the
    dot products below cost a tenth of numpy's on three elements)."""
    return (
        tuple(map(float, pitch_axis(mount_angle_rad))),
        tuple(map(float, tilt_direction(mount_angle_rad))),
    )


def _dot(a, b) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


IMU_HOLD_MAX_S = 0.05  # a DMU slower than 20 Hz holds no wheel sample back (module docstring)


@dataclass(frozen=True)
class BridgeParams:
    """The node's ROS parameters (krang_ros.params: descriptions, read only, checked at start)."""

    devices_file: str = field(
        default_factory=lambda: str(robot_devices_file()),
        metadata=_doc(
            "CAN device map; a bare name is looked up in config/ (default: the robot's SocketCAN "
            'map; the simulated node set sets can_devices.yaml)'
        ),
    )
    publish_rate_hz: float = field(
        default=500.0,
        metadata=_doc(
            'most /joint_states per second (wheel samples beyond it are skipped); 0: every wheel '
            'sample (while the DMU streams, at most one per DMU sample, just before it). '
            '/imu/data: every DMU sample'
        ),
    )
    amc_startup: bool = field(
        default=True,
        metadata=_doc('configure and enable the AMC drives through SDO at start (as amciod did)'),
    )
    sdo_timeout_s: float = field(default=0.3, metadata=_doc('SDO response timeout [s]'))
    startup_retry_s: float = field(
        default=2.0, metadata=_doc('wait before retrying a failed drive start-up [s]')
    )
    recover_timeout_s: float = field(
        default=1.0,
        metadata=_doc(
            '~/recover: how long to wait for every drive to report OPERATION_ENABLED [s]'
        ),
    )
    send_timeout_s: float = field(default=0.002, metadata=_doc('CAN send timeout [s]'))
    imu_sample_period_s: float = field(
        default=0.0,
        metadata=_doc(
            '0: DMU samples timed by arrival; > 0: by their sequence counter at this period [s]'
        ),
    )

    def __post_init__(self):
        for name in ('sdo_timeout_s', 'startup_retry_s', 'recover_timeout_s'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f'{name} must be a positive number, got {value!r}')
        for name in ('publish_rate_hz', 'send_timeout_s', 'imu_sample_period_s'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f'{name} must be a number >= 0, got {value!r}')


def describe_parameters():
    """One line per parameter (for `can_bridge --help`)."""
    return params.describe(BridgeParams) + params.describe(realtime.SchedulingParams)


class BusOpenError(RuntimeError):
    """A CAN bus of the device map cannot be opened (the message says what to do)."""


def open_bus(bus: BusConfig) -> can.BusABC:
    """can.Bus for one bus of the map, or BusOpenError with one line naming the interface and, for
    SocketCAN, the command that brings it up."""
    try:
        return can.Bus(**bus.bus_kwargs())
    except (OSError, can.CanError, ValueError) as exc:
        text = f'cannot open CAN bus {bus.name} ({bus.interface} {bus.channel}): {exc}'
        if bus.interface == 'socketcan':
            text += (
                f'; is the CAN driver loaded and the interface up? sudo ip link set '
                f'{bus.channel} up type can bitrate {CAN_BITRATE}'
            )
        raise BusOpenError(text) from exc


class _RosLogHandler(logging.Handler):
    """Forward the core's Python logging to the node's rclpy logger."""

    def __init__(self, node_logger):
        super().__init__()
        self.node_logger = node_logger

    def emit(self, record):
        text = self.format(record)
        if record.levelno >= logging.ERROR:
            self.node_logger.error(text)
        elif record.levelno >= logging.WARNING:
            self.node_logger.warning(text)
        else:
            self.node_logger.info(text)


class CanBridgeNode(Node):
    def __init__(self, pump=None, **kwargs):
        """`pump` (a bus_io.Pump): composed in one process, its frames handed over by the
        composition (krang_cli.composed) instead of a receive thread."""
        super().__init__('can_bridge', **kwargs)
        self.params = params.declare(self, BridgeParams)
        p = self.params
        devices_file = resolve_devices_file(p.devices_file)
        try:
            self.config = load_devices(devices_file)
        except ConfigError as exc:  # one line, exit code 2 (run_node), before any bus is opened
            raise params.ParameterError(f'can_bridge: devices_file {devices_file}: {exc}') from exc
        realtime.declare_thread_priority(self)
        # The core's time base (IMU filter dt, silence and command timeouts) is the time of the
        # devices: wall time (monotonic) on the robot; with use_sim_time the simulator's /clock,
        # because a simulated DMU samples in simulated time. A simulator starved of CPU runs slower
        # than the wall clock (sim_krang slips, max_lag_s): integrating its gyro over wall-clock
        # gaps overstated every pitch change by the slow-down (0.57x real time measured under load:
        # +0.10 rad IMU error within 0.5 s of the stand-up), and the gyro-dominant filter
        # (accelerometer time constant ~80 s) never took it back. /clock reaches this process on
        # another path (DDS, the executor) than the frames (UDP, the receive thread): after a
        # stall of the process the executor could take a /clock 50+ ms ahead of frames still queued
        # in the sockets, and the next wheel refresh found every device "silent" and sent zero
        # current (seen as 0 A on both wheels during a pose move, and a fall). So received frames
        # are stamped with /clock, but the checks (silence, command age) run at most
        # SIM_TIME_SLACK_S past the newest frame stamped: a device silent while others talk is
        # still caught, and when the simulator stops, its /clock stops too.
        if self.get_parameter('use_sim_time').value:
            clock = self.get_clock()
            self._frame_time = lambda: clock.now().nanoseconds * 1e-9
            self._newest_frame = self._frame_time()
            self._device_time = lambda: min(
                self._frame_time(), self._newest_frame + SIM_TIME_SLACK_S
            )
        else:
            self._frame_time = self._device_time = time.monotonic
            self._newest_frame = self._frame_time()
        # Stamps: the device time as ROS time (wall time on the robot, by one offset fixed at
        # start so the spacing of the samples stays the devices'; /clock with use_sim_time)
        self._stamp_offset = (
            0.0 if self.get_parameter('use_sim_time').value else time.time() - time.monotonic()
        )
        self.core = BridgeCore(
            self.config, clock=self._device_time, imu_sample_period_s=p.imu_sample_period_s
        )
        # imu_sample_period_s > 0: DMU samples are timed by their sequence counter
        # (sample_clock.py); kept within 0.04 s of the clock, inside the IMU's 0.05 s silence
        # timeout
        period = p.imu_sample_period_s
        self._imu_clock = SampleClock(period, lag_max_s=0.04) if period > 0 else None
        self._lock = threading.Lock()
        # The receive thread runs in bursts (a TPDO set, a DMU sample): a wheel command waiting in
        # the executor for the GIL could wait out Python's 5 ms switch interval; 0.5 ms bounds it.
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        self._send_timeout = p.send_timeout_s
        self._stop = threading.Event()
        self._send_errors: dict[str, int] = {}
        self._warn_send = Throttled(self.get_logger().warning, 1.0)
        self._warn_joint_cmd = Throttled(self.get_logger().warning, 1.0)
        self._receive_errors: dict[str, str] = {}
        self._startup_status: dict[str, str] = {}
        self._sdo_lock = threading.Lock()  # one SDO user at a time: start-up or recover
        self._sdo_timeout = p.sdo_timeout_s
        self._recover_timeout = p.recover_timeout_s
        self._published_fault: str | None = None
        self._joint_period = 1.0 / p.publish_rate_hz if p.publish_rate_hz > 0 else 0.0
        self._joints_published_at = -math.inf
        self._imu_at, self._imu_interval = -math.inf, math.inf  # arrivals of /imu/data samples
        self._held_joints = None  # a wheel sample's /joint_states waiting for the next /imu/data
        self.published = {names.IMU: 0, names.JOINT_STATES: 0}

        self._log_handler = _RosLogHandler(self.get_logger())
        logging.getLogger('krang_can_bridge').addHandler(self._log_handler)
        logging.getLogger('krang_can_bridge').setLevel(logging.INFO)

        self.buses: dict[str, can.BusABC] = {}
        try:
            for name in self.config.buses_in_use():
                self.buses[name] = open_bus(self.config.buses[name])
        except BusOpenError:
            for b in self.buses.values():
                b.shutdown()
            logging.getLogger('krang_can_bridge').removeHandler(self._log_handler)
            raise
        queues = {}  # bus -> receive queue granted (bytes), where the bus has a socket
        for name, bus in self.buses.items():
            receive_only(bus, self.core.received_ids(name))
            queues[name] = enlarge_receive_buffer(bus)
        self.canopen = canopen.Network(self.buses[self.config.wheels.bus])

        qos = topics.QOS
        self.joint_pub = self.create_publisher(
            JointState, names.relative(names.JOINT_STATES), qos[names.JOINT_STATES]
        )
        self.imu_pub = self.create_publisher(Imu, names.relative(names.IMU), qos[names.IMU])
        self.diag_pub = self.create_publisher(
            DiagnosticArray, names.relative(names.DIAGNOSTICS), qos[names.DIAGNOSTICS]
        )
        self.fault_pub = self.create_publisher(
            String, names.private(names.DRIVE_FAULT), topics.LATCHED
        )
        self.publish_fault()
        self.create_service(Trigger, '~/recover', self.on_recover)
        self.create_subscription(  # as bytes: the control path (krang_ros.wire)
            JointState,
            names.relative(names.WHEEL_EFFORT_CMD),
            self.on_wheel_effort,
            qos[names.WHEEL_EFFORT_CMD],
            raw=True,
        )
        self.create_subscription(
            JointState,
            names.relative(names.JOINT_POSITION_CMD),
            self.on_joint_position,
            qos[names.JOINT_POSITION_CMD],
        )

        # watchdog only: sends while commands stop (the commands themselves send their frames)
        self.watchdog_timer = self.create_timer(
            1.0 / self.config.wheels.command_rate_hz, self.wheel_watchdog
        )
        self.create_timer(1.0 / self.config.powercube.poll_rate_hz, self.poll_modules)
        self.create_timer(0.5 * self.config.imu.stream_toggle_retry_s, self.check_imu_stream)
        self.create_timer(1.0, self.publish_diagnostics)
        # frames only once every publisher exists (a sample completed earlier ended the thread)
        imu_first = dict(sorted(self.buses.items(), key=lambda b: b[0] != self.config.imu.bus))
        self.reader = (pump.reader if pump else BusReader)(
            imu_first, self.on_received, self.on_bus_error
        )
        # the PowerCube polls and moves: off the executor, which sends the wheel currents
        # (composed, in order with everything else: the run is the same every time)
        self.sender = None if pump else SendThread(self.send, self.on_send_error)

        for drive in self.config.wheels.drives:
            self._startup_status[drive.joint] = 'pending'
            if p.amc_startup:
                self.core.inhibit(
                    f'startup/{drive.joint}', f'{drive.joint}: AMC start-up not done'
                )
        self._startup_thread = threading.Thread(
            target=self._startup_worker, args=(p.amc_startup, p.startup_retry_s), daemon=True
        )
        self._startup_thread.start()
        self._watchdog_thread = threading.Thread(target=self._watchdog_worker, daemon=True)
        self._watchdog_thread.start()
        self.get_logger().info(
            'can_bridge on '
            + ', '.join(
                f'{n}={self.config.buses[n].interface}:{self.config.buses[n].channel}'
                + (f' (receive queue {queues[n] >> 10} KiB)' if queues[n] else '')
                for n in self.buses
            )
        )

    # ---- CAN I/O --------------------------------------------------------------------------------
    def on_received(self, bus: str, msg: can.Message) -> None:
        if self._stop.is_set():  # closing: the drives' reaction to our silence is expected
            return
        t_in = trace.now() if trace.ON else 0.0
        with self._lock:
            now = arrived = self._frame_time()
            if now > self._newest_frame:
                self._newest_frame = now
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
                elif joints is not None:  # out just before the next /imu/data (docstring)
                    self._held_joints = joints
            # a drive fault this frame latched: zero current at once, not at the next command
            stop = (
                self.core.wheel_current_frames(0.0, 0.0, self._device_time())
                if self.core.fault_reason and not fault
                else []
            )
        self.send(stop)
        for sample_out in (held, out):
            if sample_out is None:
                continue
            try:
                sample_out[0].publish(sample_out[1])
            except RCLError:
                if self.context.ok():
                    raise
                return  # shut down by a signal under this thread; close() follows
            self.published[sample_out[2]] += 1
        if trace.ON and out is not None and out[2] == names.IMU:
            trace.record('imu_in', out[3], msg.timestamp, t_in, trace.now())
        if (
            bus == self.config.wheels.bus
            and not msg.is_error_frame
            and msg.arbitration_id in self.canopen.subscribers  # SDO responses, for the start-up
        ):
            self.canopen.notify(msg.arbitration_id, msg.data, msg.timestamp)

    def _imu_due(self, now: float) -> bool:
        """Whether the DMU streams: its last sample came less than 1.5 of its intervals before
        `now` (arrival times), so a wheel sample's /joint_states waits for the next one."""
        interval = self._imu_interval
        return interval <= IMU_HOLD_MAX_S and now - self._imu_at < 1.5 * interval

    def _imu_out(self, now: float):
        """(publisher, message as CDR bytes, topic, stamp) of the DMU sample a frame completed at
        `now`, or None while the filter has no estimate; called under the lock."""
        imu = self.core.imu_state(now)
        if imu is None:
            return None
        stamp = self._stamp(imu.stamp)
        return self.imu_pub, self._imu_message(imu, stamp), names.IMU, stamp

    def _joints_out(self, now: float):
        """As _imu_out, of the wheel sample completed at `now`, and its time; None beyond
        publish_rate_hz (counted from the last one released) or with no joint known. Built as the
        sample completes, so that a held one costs the next /imu/data only its publication."""
        if now - self._joints_published_at < 0.999 * self._joint_period:
            return None
        joints = self.core.joint_state(now)
        if not joints.names:
            return None
        stamp = self._stamp(now)
        msg = wire.joint_state_bytes(
            stamp, joints.names, joints.positions, joints.velocities, joints.efforts
        )
        return self.joint_pub, msg, names.JOINT_STATES, stamp, now

    def _released(self, joints):
        """`joints` (from _joints_out, or None) on its way out: the publish rate counts from it."""
        if joints is not None:
            self._joints_published_at = joints[4]
        return joints

    def _stamp(self, t: float):
        return messages.stamp(t + self._stamp_offset)

    def _imu_sample_time(self, msg: can.Message, now: float) -> float:
        """Time of a DMU frame from its sequence counter (see imu_sample_period_s); `now` if
        undecodable."""
        try:
            seq = self.core.dmu.decode(msg).sequence
        except Exception:  # noqa: BLE001 - the core counts the malformed frame
            return now
        return self._imu_clock.time_of(seq, now)

    def on_bus_error(self, bus: str, exc: Exception) -> None:
        self._receive_errors[bus] = f'{type(exc).__name__}: {exc}'
        self.get_logger().error(f'CAN receive on {bus} stopped: {exc}')

    def send_later(self, frames: list[BusFrame], key=None) -> None:
        """Frames no control loop waits for: sent by the send thread, a newer batch of the same
        `key` replacing one still waiting (see bus_io.SendThread)."""
        if self.sender is None:
            self.send(frames)
        else:
            self.sender.put(frames, key)

    def on_send_error(self, exc: Exception) -> None:
        if not self._stop.is_set():
            self.get_logger().error(f'CAN send thread: {type(exc).__name__}: {exc}')

    def send(self, frames: list[BusFrame]) -> None:
        for bus, msg in frames:
            try:
                self.buses[bus].send(msg, timeout=self._send_timeout)
            except can.CanError as exc:
                self._send_errors[bus] = self._send_errors.get(bus, 0) + 1
                self._warn_send(f'send on {bus} failed: {exc}')

    def _watchdog_worker(self) -> None:
        """Send the drives' watchdog frames every period; the core withholds them when the wheel
        command loop is quiet, and a hung core (lock held) stops them too."""
        period = self.config.wheels.watchdog.period_s
        if self.config.wheels.watchdog.mechanism == 'none':
            return
        due = time.monotonic()
        while not self._stop.wait(max(0.0, due - time.monotonic())):
            due = max(due + period, time.monotonic())
            with self._lock:
                frames = self.core.watchdog_frames(self._device_time())
            self.send(frames)

    def _enable_drive(self, drive) -> list[str]:
        """The start-up sequence (fault reset, watchdog, enable) of one drive; its mismatches."""
        with self._lock:
            self.core.drive_started(drive.joint, False)
        with self._sdo_lock:
            mismatches = amc_proto.run_startup(
                self.canopen, drive, self.config.wheels, self._sdo_timeout
            )
        with self._lock:
            self.core.drive_started(drive.joint, not mismatches)
        return mismatches

    def _startup_worker(self, amc_startup: bool, retry_s: float) -> None:
        with self._lock:
            frames = self.core.startup_frames()
        self.send(frames)
        if not amc_startup:
            return
        for drive in self.config.wheels.drives:
            key = f'startup/{drive.joint}'
            while not self._stop.is_set():
                try:
                    mismatches = self._enable_drive(drive)
                except Exception as exc:  # noqa: BLE001 - SDO timeout/abort or bus error: retry
                    self._startup_status[drive.joint] = f'failed: {type(exc).__name__}: {exc}'
                    self.get_logger().warning(
                        f'{drive.joint} start-up failed ({exc}); retrying',
                        throttle_duration_sec=10.0,
                    )
                    self._stop.wait(retry_s)
                    continue
                with self._lock:
                    if mismatches:
                        self._startup_status[drive.joint] = 'constants mismatch: ' + '; '.join(
                            mismatches
                        )
                        self.core.inhibit(key, '; '.join(mismatches))
                        self.get_logger().error(self._startup_status[drive.joint])
                    else:
                        self._startup_status[drive.joint] = 'enabled'
                        self.core.inhibit(key, None)
                break

    @property
    def startup_status(self) -> dict[str, str]:
        """Each drive's start-up: 'pending', 'enabled', 'failed: ...' or 'constants
        mismatch: ...'."""
        return dict(self._startup_status)

    # ---- drive faults ---------------------------------------------------------------------------
    def publish_fault(self) -> None:
        """The latched drive fault on DRIVE_FAULT, whenever it changes ('' once at start-up)."""
        with self._lock:
            reason = self.core.fault_reason
        if reason != self._published_fault:
            self._published_fault = reason
            self.fault_pub.publish(String(data=reason))

    def on_recover(self, request, response):
        """Runs the recovery in a thread and, until it ends, keeps the wheel command loop going
        (zero current while latched), so the drives' watchdog goes on seeing a live bridge. The
        other callbacks wait (rclpy's executor would starve them while a coroutine awaits a
        thread's result)."""
        result = []
        worker = threading.Thread(target=lambda: result.append(self._recover()), daemon=True)
        worker.start()
        period = 1.0 / self.config.wheels.command_rate_hz
        while worker.is_alive():
            self.send_wheel_commands()
            worker.join(period)
        response.success, response.message = result[0] if result else (False, 'recover failed')
        if response.success:
            self.get_logger().info(f'recover: {response.message}')
        else:
            self.get_logger().warning(f'recover: {response.message}')
        self.publish_fault()
        return response

    def _recover(self) -> tuple[bool, str]:
        """DS402 fault reset and enable sequence on every drive, then unlatch if all report
        OPERATION_ENABLED (BridgeCore.recover_status)."""
        with self._lock:
            reason = self.core.fault_reason
        if not reason:
            return True, 'no drive fault latched'
        for drive in self.config.wheels.drives:
            try:
                mismatches = self._enable_drive(drive)
            except Exception as exc:  # noqa: BLE001 - SDO timeout/abort or bus error
                return False, (
                    f'{drive.joint}: fault reset and enable failed '
                    f'({type(exc).__name__}: {exc}); fault still latched: {reason}'
                )
            if mismatches:
                return False, '; '.join(mismatches)
        since = self._frame_time()
        deadline = time.monotonic() + self._recover_timeout
        while True:
            with self._lock:
                ok, why = self.core.recover_status(since)
                if ok:
                    self.core.clear_fault()
                    return True, f'recovered from: {reason}'
            if ok is False or time.monotonic() > deadline:
                return False, f'refused: {why}; fault still latched: {reason}'
            time.sleep(0.01)

    # ---- commands -------------------------------------------------------------------------------
    def on_wheel_effort(self, raw: bytes) -> None:
        """Sends the current frames at once (the wheels' efforts by name; anything else, bytes
        that are not a JointState included, is one invalid command: zero current on both
        wheels)."""
        t_in = trace.now() if trace.ON else 0.0
        try:
            msg = wire.read_joint_state(raw)
        except wire.WireError:
            msg = None
        efforts = None if msg is None else messages.wheel_efforts(msg, names.WHEEL_JOINTS)
        with self._lock:
            self.core.set_wheel_effort_command(efforts, self._device_time())
            frames = self.core.wheel_command_frames(self._device_time())
        self.send(frames)
        if trace.ON and msg is not None:
            trace.record('cmd_out', msg.stamp, t_in, trace.now())
        self.watchdog_timer.reset()  # quiet while commands flow (it would send nothing)
        self.publish_fault()  # the watchdog's other job

    def on_joint_position(self, msg: JointState) -> None:
        if len(msg.position) != len(msg.name):
            self._warn_joint_cmd(
                f'{names.JOINT_POSITION_CMD}: name and position lengths differ; ignored'
            )
            return
        with self._lock:
            frames = self.core.joint_position_frames(
                dict(zip(msg.name, msg.position)), self._device_time()
            )
        # a newer target for the same modules replaces one not yet sent
        self.send_later(frames, ('move', *sorted({(f.bus, f.msg.arbitration_id) for f in frames})))

    def send_wheel_commands(self) -> None:
        with self._lock:
            frames = self.core.wheel_command_frames(self._device_time())
        self.send(frames)
        self.publish_fault()

    def wheel_watchdog(self) -> None:
        with self._lock:
            frames = self.core.wheel_watchdog_frames(self._device_time())
        self.send(frames)
        self.publish_fault()

    def poll_modules(self) -> None:
        with self._lock:
            frames = self.core.poll_frames()
        self.send_later(frames, 'poll')

    def check_imu_stream(self) -> None:
        with self._lock:
            frames = self.core.imu_stream_frames(self._device_time())
        if frames:
            self.get_logger().info('DMU silent: sending the stream toggle')
        self.send(frames)

    # ---- state out ------------------------------------------------------------------------------
    def _imu_message(self, imu, stamp) -> bytes:
        """The /imu/data message (CDR bytes, messages.imu): the DMU's rates and specific force
        turned by the mount angle into x forward, y left, z up (at zero pitch); the pitch rate is
        the filtered one."""
        e, d = _sensor_axes(self.config.imu.mount_angle_rad)
        w, f = imu.rates, imu.specific_force
        return messages.imu(
            stamp,
            self.config.imu.frame_id,
            imu.pitch,
            imu.pitch_variance,
            (-_dot(d, w), imu.pitch_rate, w[2]),
            (-_dot(d, f), _dot(e, f), f[2]),
        )

    def publish_diagnostics(self) -> None:
        with self._lock:
            reports = self.core.diagnostics(self._device_time())
        statuses = [
            messages.diagnostic_status(
                r.name, messages.LEVEL_NAMES[r.level], r.message, r.values, HARDWARE_ID
            )
            for r in reports
        ]
        for bus in self.buses:
            sent_err, recv_err = self._send_errors.get(bus, 0), self._receive_errors.get(bus)
            if sent_err or recv_err:
                statuses.append(
                    messages.diagnostic_status(
                        f'can_bridge: bus {bus} I/O',
                        'error' if recv_err else 'warn',
                        recv_err or f'{sent_err} send errors',
                        {'send_errors': sent_err, 'receive_error': recv_err},
                        HARDWARE_ID,
                    )
                )
        statuses.append(
            messages.diagnostic_status(
                'can_bridge: samples published',
                'ok',
                ', '.join(f'{n} {topic}' for topic, n in self.published.items()),
                {topic: str(n) for topic, n in self.published.items()},
                HARDWARE_ID,
            )
        )
        for joint, status in self._startup_status.items():
            statuses.append(
                messages.diagnostic_status(
                    f'can_bridge: amc/{joint} start-up',
                    'ok' if status == 'enabled' else 'warn',
                    status,
                    hardware_id=HARDWARE_ID,
                )
            )
        self.diag_pub.publish(messages.diagnostic_array(self.get_clock().now().to_msg(), statuses))

    # ---- shutdown -------------------------------------------------------------------------------
    def close(self) -> None:
        """Zero the wheel currents, stop the threads, release the buses."""
        self._stop.set()
        try:
            with self._lock:
                frames = self.core.wheel_current_frames(0.0, 0.0, self._device_time())
            self.send(frames)
        except Exception:  # noqa: BLE001 - best effort on the way out
            pass
        self.reader.stop()
        if self.sender is not None:
            self.sender.stop()
        for b in self.buses.values():
            b.shutdown()
        logging.getLogger('krang_can_bridge').removeHandler(self._log_handler)


def main(args=None):
    """Exit code 1 with one line on stderr when a bus cannot be opened (no traceback)."""
    try:
        return run_node(CanBridgeNode, args)
    except BusOpenError as exc:
        print(f'can_bridge: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return 1


if __name__ == '__main__':
    sys.exit(main())
