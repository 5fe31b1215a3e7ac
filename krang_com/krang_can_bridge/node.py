"""can_bridge: the thin rclpy shell around krang_can_bridge.runtime.BridgeRuntime (the time base,
the receive path, the held wheel sample, the drives' start-up and recovery, all tested without
ROS), which drives krang_can_bridge.bridge.BridgeCore. The node declares the parameters, opens the
buses and wires the runtime to topics, a service and timers.

Buses come from the device map (parameter `devices_file`, default the robot's SocketCAN map
config/can_devices_robot.yaml; a bare file name is looked up in config/, so the simulated node set
passes `can_devices.yaml` in config/sim_params.yaml). A bus that cannot be opened ends the node
with one line naming the interface (and, for SocketCAN, the `ip link` command) and exit code 1.
One receive thread (bus_io.BusReader) feeds the frames of every bus to the runtime, so the
executor never blocks on CAN; the kernel passes it only the ids the core reads
(BridgeCore.received_ids, bus_io.receive_only), and each socket's receive queue is enlarged
(bus_io.enlarge_receive_buffer) so that a stall of the thread delays frames instead of losing
them. The node is event-driven: the receive thread publishes each sample as soon as the core
says its frames are in (rclpy publishers may be called from any thread), and the wheel current
frames go out from the command callback. The control path's messages (/imu/data, /joint_states,
the wheel command) are written and read as their serialized bytes (krang_ros.wire). The PowerCube
polls and moves go out from a send thread (bus_io.SendThread). The AMC start-up and the recovery
(blocking SDO transfers through canopen) run in their own threads, and so does the drive-side
watchdog's heartbeat, which the core withholds when the wheel command loop (the executor) stops
running (docs/can.md).

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
- publishes /can_bridge/drive_fault (krang_com_interfaces/DriveFault, latched): the latched drive
  fault, active with its reason, or clear (BridgeCore: a FAULT or EMCY of any drive stops both
  wheels; the frame that latches it sends zero current at once);
- publishes /can_bridge/arm_fault (krang_com_interfaces/ArmFault, latched): a PowerCube module
  that answered and fell silent, with its joints and the reason, or clear (BridgeCore: the wheels
  keep balancing, the joint stays in /joint_states at its last position, no commands to it);
- serves ~/recover (std_srvs/Trigger, /can_bridge/recover): DS402 fault reset and the enable
  sequence (the start-up again), then unlatches only if every drive reports OPERATION_ENABLED;
  an arm fault is cleared only once every module answers; refused with the reason otherwise.

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

import logging
import math
import sys
from dataclasses import dataclass, field

import can
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from krang_com_interfaces.msg import ArmFault, DriveFault
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_srvs.srv import Trigger

from krang_can_bridge.bus_io import enlarge_receive_buffer, receive_only
from krang_can_bridge.config import (
    CAN_BITRATE,
    BusConfig,
    ConfigError,
    load_devices,
    resolve_devices_file,
    robot_devices_file,
)
from krang_can_bridge.runtime import BridgeRuntime, imu_vectors
from krang_can_bridge.sample_clock import TimeBase
from krang_core import names, params
from krang_core.log import Throttled
from krang_ros import messages, realtime, topics, trace, wire
from krang_ros.params import declare
from krang_ros.spin import run_node

HARDWARE_ID = 'krang_can'


def _doc(text: str) -> dict:
    return {'doc': text}


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
        self.params = params_ = declare(self, BridgeParams)
        devices_file = resolve_devices_file(params_.devices_file)
        try:
            self.config = load_devices(devices_file)
        except ConfigError as exc:  # one line, exit code 2 (run_node), before any bus is opened
            raise params.ParameterError(f'can_bridge: devices_file {devices_file}: {exc}') from exc
        realtime.declare_thread_priority(self)
        # The receive thread runs in bursts (a TPDO set, a DMU sample): a wheel command waiting in
        # the executor for the GIL could wait out Python's 5 ms switch interval; 0.5 ms bounds it.
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0005))
        self._warn_joint_cmd = Throttled(self.get_logger().warning, 1.0)
        self._log_handler = _RosLogHandler(self.get_logger())
        logging.getLogger('krang_can_bridge').addHandler(self._log_handler)
        logging.getLogger('krang_can_bridge').setLevel(logging.INFO)

        buses: dict[str, can.BusABC] = {}
        try:
            for name in self.config.buses_in_use():
                buses[name] = open_bus(self.config.buses[name])
        except BusOpenError:
            for b in buses.values():
                b.shutdown()
            logging.getLogger('krang_can_bridge').removeHandler(self._log_handler)
            raise
        clock = self.get_clock()
        sim_clock = (
            (lambda: clock.now().nanoseconds * 1e-9)
            if self.get_parameter('use_sim_time').value
            else None
        )
        self.runtime = BridgeRuntime(
            self.config,
            buses,
            publish=self._publish,
            stamp=messages.stamp,
            encode_imu=self._imu_message,
            encode_joints=lambda j, stamp: wire.joint_state_bytes(
                stamp, j.names, j.positions, j.velocities, j.efforts
            ),
            time_base=TimeBase(sim_clock),
            publish_rate_hz=params_.publish_rate_hz,
            imu_sample_period_s=params_.imu_sample_period_s,
            send_timeout_s=params_.send_timeout_s,
            sdo_timeout_s=params_.sdo_timeout_s,
            recover_timeout_s=params_.recover_timeout_s,
            amc_startup=params_.amc_startup,
        )
        self.core = self.runtime.core
        queues = {}  # bus -> receive queue granted (bytes), where the bus has a socket
        for name, bus in buses.items():
            receive_only(bus, self.core.received_ids(name))
            queues[name] = enlarge_receive_buffer(bus)

        qos = topics.QOS
        self.joint_pub = self.create_publisher(
            JointState, names.relative(names.JOINT_STATES), qos[names.JOINT_STATES]
        )
        self.imu_pub = self.create_publisher(Imu, names.relative(names.IMU), qos[names.IMU])
        self._sample_pubs = {names.JOINT_STATES: self.joint_pub, names.IMU: self.imu_pub}
        self.diag_pub = self.create_publisher(
            DiagnosticArray, names.relative(names.DIAGNOSTICS), qos[names.DIAGNOSTICS]
        )
        self.fault_pub = self.create_publisher(
            DriveFault, names.private(names.DRIVE_FAULT), topics.LATCHED
        )
        self.arm_fault_pub = self.create_publisher(
            ArmFault, names.private(names.ARM_FAULT), topics.LATCHED
        )
        self.publish_fault()
        self.publish_arm_fault()
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
        self.create_timer(
            0.5 * self.config.imu.stream_toggle_retry_s, self.runtime.check_imu_stream
        )
        self.create_timer(1.0, self.publish_diagnostics)
        # frames only once every publisher exists (a sample completed earlier ended the thread)
        self.runtime.start(params_.startup_retry_s, pump=pump, on_frame=self.on_received)
        self.get_logger().info(
            'can_bridge on '
            + ', '.join(
                f'{n}={self.config.buses[n].interface}:{self.config.buses[n].channel}'
                + (f' (receive queue {queues[n] >> 10} KiB)' if queues[n] else '')
                for n in buses
            )
        )

    @property
    def buses(self) -> dict[str, can.BusABC]:
        return self.runtime.buses

    @property
    def published(self) -> dict[str, int]:
        return self.runtime.published

    @property
    def startup_status(self) -> dict[str, str]:
        return self.runtime.startup_status

    # ---- CAN I/O --------------------------------------------------------------------------------
    def on_received(self, bus: str, msg: can.Message) -> None:
        t_in = trace.now() if trace.ON else 0.0
        imu = self.runtime.on_received(bus, msg)
        if trace.ON and imu is not None:
            trace.record('imu_in', imu.stamp, msg.timestamp, t_in, trace.now())

    def _publish(self, topic: str, message) -> bool:
        """A sample from the receive thread (rclpy publishers may be called from any thread);
        False once a signal shut the context down under the thread (close() follows)."""
        try:
            self._sample_pubs[topic].publish(message)
        except RCLError:
            if self.context.ok():
                raise
            return False
        return True

    def _imu_message(self, imu, stamp) -> bytes:
        """The /imu/data message (CDR bytes, messages.imu)."""
        angular_velocity, linear_acceleration = imu_vectors(imu, self.config.imu.mount_angle_rad)
        return messages.imu(
            stamp,
            self.config.imu.frame_id,
            imu.pitch,
            imu.pitch_variance,
            angular_velocity,
            linear_acceleration,
        )

    # ---- drive faults ---------------------------------------------------------------------------
    def publish_fault(self) -> None:
        """The latched drive fault on DRIVE_FAULT, whenever it changes (clear once at start-up)."""
        reason = self.runtime.fault_changed()
        if reason is not None:
            self.fault_pub.publish(messages.drive_fault(self.get_clock().now().to_msg(), reason))

    def publish_arm_fault(self) -> None:
        """The latched arm fault on ARM_FAULT, whenever it changes (clear once at start-up)."""
        fault = self.runtime.arm_fault_changed()
        if fault is not None:
            self.arm_fault_pub.publish(messages.arm_fault(self.get_clock().now().to_msg(), *fault))

    def poll_modules(self) -> None:
        """The PowerCube polls, and the arm fault a module's silence latched."""
        self.runtime.poll_modules()
        self.publish_arm_fault()

    def on_recover(self, request, response):
        """The recovery (BridgeRuntime.recover_keeping_alive). The other callbacks wait (rclpy's
        executor would starve them while a coroutine awaits a thread's result)."""
        response.success, response.message = self.runtime.recover_keeping_alive()
        if response.success:
            self.get_logger().info(f'recover: {response.message}')
        else:
            self.get_logger().warning(f'recover: {response.message}')
        self.publish_fault()
        self.publish_arm_fault()
        return response

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
        self.runtime.wheel_effort(efforts)
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
        self.runtime.joint_positions(dict(zip(msg.name, msg.position)))

    def wheel_watchdog(self) -> None:
        self.runtime.wheel_watchdog()
        self.publish_fault()

    # ---- state out ------------------------------------------------------------------------------
    def publish_diagnostics(self) -> None:
        statuses = [
            messages.diagnostic_status(
                r.name, messages.LEVEL_NAMES[r.level], r.message, r.values, HARDWARE_ID
            )
            for r in self.runtime.diagnostics()
        ]
        self.diag_pub.publish(messages.diagnostic_array(self.get_clock().now().to_msg(), statuses))

    # ---- shutdown -------------------------------------------------------------------------------
    def close(self) -> None:
        """Zero the wheel currents, stop the threads, release the buses."""
        self.runtime.close()
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
