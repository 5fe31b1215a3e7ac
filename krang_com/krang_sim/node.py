"""sim_krang: the simulated Krang behind the same CAN frames as the real robot.

A physics thread steps the plant (`plant`: a registered engine of krang_sim.plant, by default the
reduced WIP; `plant_model`: an extended model of `krang discrepancy`; `effects`: the true robot's
effects from the registry of krang_model.effects, on top of it) at
`physics_rate_hz`, and paces itself at `real_time_factor` times wall time (1 = real time, 0 = as
fast as the CPU allows). What the devices report of its motion is the one sensor model's
(krang_sim.sensors). When the CPU cannot keep up it falls behind by at most `max_lag_s` and then
slows down, instead of catching up in bursts the controller cannot see (under lockstep, below, it
sees a catch-up sample by sample: config/sim_params.yaml allows it more). The device emulators of
devices.py answer the bridge on the buses of the device map: AMC drives (current commands in, TPDO
feedback out), the DMU IMU and the PowerCube modules, which move the body joints at their speed
limits. With `publish_clock` the node publishes /clock (at `clock_rate_hz`, right after the sensor
frames of that step), so nodes running with use_sim_time follow the simulated time whether it runs
faster or slower than real time: `krang demo` runs the node set that way, because a simulator
starved of CPU slows down. Ground truth for evaluation goes to /sim_krang/ground_truth (every 0.1 s
of simulated time).

Lockstep (`lockstep`): after each sensor sample the physics waits until the wheel current frames
that answer it are on the bus (an RPDO from every drive, applied to the emulated drives before the
physics goes on), so the node set runs as fast as the control path allows (with
`real_time_factor` 0; real time until the commands come) and every command acts from the same
simulated time in every run, however late it came in wall time. It waits on the bus, not on
/wheel_effort_cmd: the current takes effect when the drive receives its frame, and a message on the
topic can overtake the bridge's frames. Every current frame after a sample is an answer because
can_bridge sends them only from a command (its watchdog timer sends zero current once commands
stop, and never repeats a command in force: a repeat let the physics run on, 130 ms once, while
a loaded controller was late, and the robot fell). The topic arms it: lockstep holds while wheel
commands arrive (within `lockstep_timeout_s` of wall time), so a node set without a controller, or
one that stopped, still runs; a sample left unanswered that long is counted (`lockstep_misses` in
/diagnostics) and the physics goes on. The physics thread reads the topic's newest stamp at each
sample (a `Polled` subscription: no executor wake per command); /diagnostics reports when the
lockstep first held (`lockstep_first_armed_s`). The answer acts from `lockstep_delay_s` after
its sample in simulated time (whole physics steps, less than one sample period), the latency the
simulated robot sees, whatever the wall-clock one was.

Composed (constructed with a bus_io.Pump, krang_cli.composed): no physics or bus thread. The
composition calls `advance()`, which steps the physics up to the step from which the answer to the
next sample acts, and then delivers everything the sample caused before the next call: the
simulator then waits for the whole node set, not only the wheel command, and a session gives the
same result in every run.

Fault injection: `silent_devices` (string array, settable at run time, e.g. through
/sim_krang/set_parameters) silences devices as devices.py describes: 'imu', a wheel joint for its
AMC drive, or a body joint for its PowerCube modules; [] restores them. The change is logged and
reported at once on /diagnostics with the simulated time it took effect (`silent_since_s`).
"""

import dataclasses
import math
import sys
import threading
import time

import can
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from krang_can_bridge.bus_io import BusReader, receive_only
from krang_can_bridge.config import default_devices_file, load_devices
from krang_can_bridge.protocols import amc as amc_proto
from krang_model.beta import load_beta
from krang_model.robot import load_krang
from krang_core import names, params
from krang_ros import messages, topics
from krang_core.log import Throttled
from krang_ros.params import declare
from krang_ros.spin import Polled, run_node, take_latest

from .devices import KrangCanDevices
from .plant import BUILTIN, PLANTS, make_plant, plant_terms
from .sensors import SensorModel, SensorNoise
from .session_config import resolve_config_file

GROUND_TRUTH_FIELDS = ('t', 'q_base', 'x_m', 'balance_pitch', 'current_left_a', 'current_right_a')


def _doc(default, text):
    return dataclasses.field(default=default, metadata={'doc': text})


@dataclasses.dataclass(frozen=True)
class SimNodeParams:
    """sim_krang's parameters (all read at start, except `silent_devices`)."""

    devices_file: str = _doc(
        '',
        "device map; '' = config/can_devices.yaml (the simulator's "
        'udp_multicast buses); a bare name is looked up in config/',
    )
    true_beta: str = _doc(
        '',
        "the hidden true beta file; '' = config/sim_true_beta.yaml; a bare "
        'name is looked up in config/',
    )
    initial_pose: tuple[float, ...] = _doc(
        (), 'the 16 body joints in pose order, rad (empty = all zero)'
    )
    initial_q_base: float = _doc(math.nan, 'initial base pitch, rad (NaN = resting on the caster)')
    plant: str = _doc('reduced', f'the physics engine: one of {", ".join(sorted(BUILTIN))}')
    effects: tuple[str, ...] = _doc(
        (),
        "the true robot's physical effects, 'key=value' in the effect's unit (krang_model."
        "effects, e.g. 'torque_constant=0.8', 'wheel_coulomb_friction=4'; empty = nominal)",
    )
    plant_model: str = _doc(
        '',
        'an extended model written by `krang discrepancy` (its extended_model.yaml): the true '
        "robot's effects, with `effects` applied on top ('' = the nominal robot)",
    )
    physics_rate_hz: float = _doc(1000.0, 'physics steps per simulated second, > 0')
    feedback_rate_hz: float = _doc(250.0, "the DMU's and the drives' sample rate, Hz, > 0")
    real_time_factor: float = _doc(
        1.0, 'pace: 1 = real time, 0 = as fast as the CPU (or the lockstep) allows, >= 0'
    )
    publish_clock: bool = _doc(False, 'publish /clock for nodes with use_sim_time')
    clock_rate_hz: float = _doc(0.0, '/clock rate, Hz (0 = with each sensor sample)')
    seed: int = _doc(0, 'seed of the sensor noise')
    max_lag_s: float = _doc(0.02, 'catch up at most this far behind the wall clock, then slip, s')
    lockstep: bool = _doc(
        False,
        'advance the physics only when the commands answering the last sample are on the bus',
    )
    lockstep_timeout_s: float = _doc(
        0.5,
        'wall time to wait for an answer before going on (a '
        'miss, counted in /diagnostics), s, > 0',
    )
    lockstep_delay_s: float = _doc(
        0.001,
        'simulated latency from a sample to the action of its '
        'answer, s (less than one sample period)',
    )
    gil_switch_interval_s: float = _doc(
        0.001, "Python's thread switch interval while the physics runs behind real time, s, > 0"
    )

    def __post_init__(self):
        for name in (
            'physics_rate_hz',
            'feedback_rate_hz',
            'lockstep_timeout_s',
            'gil_switch_interval_s',
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0, got {getattr(self, name)}')
        if (
            self.real_time_factor < 0
            or self.clock_rate_hz < 0
            or self.max_lag_s < 0
            or self.lockstep_delay_s < 0
        ):
            raise ValueError(
                'real_time_factor, clock_rate_hz, max_lag_s and lockstep_delay_s must be >= 0'
            )
        if self.plant not in BUILTIN and self.plant not in PLANTS:
            raise ValueError(
                f'plant must be one of {sorted({*BUILTIN, *PLANTS})}, got {self.plant!r}'
            )


def describe_parameters():
    lines = params.describe(SimNodeParams)
    lines.append(
        'silent_devices (list of str, []): devices that stop transmitting (fault '
        "injection: 'imu', a wheel joint, a body joint); settable at run time"
    )
    return lines


class SimKrangNode(Node):
    def __init__(self, pump=None, **kwargs):
        """`pump` (a bus_io.Pump): composed in one process, stepped by `advance()` (no physics
        or bus thread)."""
        super().__init__('sim_krang', **kwargs)
        self.robot = load_krang()
        cfg = declare(self, SimNodeParams)
        devices_file = str(resolve_config_file(cfg.devices_file, default_devices_file().name))
        truth_file = str(resolve_config_file(cfg.true_beta, 'sim_true_beta.yaml'))
        pose = list(cfg.initial_pose) or [0.0] * len(self.robot.pose_joints)
        if len(pose) != len(self.robot.pose_joints):
            raise params.ParameterError(
                f'sim_krang: initial_pose has {len(pose)} values, the '
                f'robot {len(self.robot.pose_joints)} body joints'
            )
        q_base = cfg.initial_q_base
        # what the simulated robot is, for its log line and /diagnostics
        self.plant_name = cfg.plant
        described = [f'extended model {cfg.plant_model}'] if cfg.plant_model else []
        self.true_robot = ', '.join(described + list(cfg.effects)) or 'nominal'
        self.rate = cfg.physics_rate_hz
        self.feedback_every = max(1, round(self.rate / cfg.feedback_rate_hz))
        self.factor = cfg.real_time_factor
        self.publish_clock = cfg.publish_clock
        # /clock every `clock_every` physics steps (default: with each sensor feedback). Every node
        # on use_sim_time pays for each /clock message (rclpy re-evaluates its timers), so the rate
        # is the coarsest the nodes' timers need.
        clock_rate = cfg.clock_rate_hz or self.rate / self.feedback_every
        self.clock_every = max(1, round(self.rate / clock_rate))
        seed = cfg.seed
        try:
            terms = plant_terms(self.robot, cfg.effects, cfg.plant_model or None)
        except (KeyError, ValueError, OSError) as err:
            raise params.ParameterError(f'sim_krang: effects / plant_model: {err}') from None
        self.config = load_devices(devices_file)
        true_beta = load_beta(truth_file, self.robot)
        # the plant (its truth is read only for /sim_krang/ground_truth and diagnostics)
        self.sim = make_plant(
            cfg.plant,
            self.robot,
            true_beta,
            np.array(pose),
            q_base=None if math.isnan(q_base) else q_base,
            terms=terms,
            dt=1.0 / self.rate,
        )
        # the one sensor model: encoder counts, IMU misalignment and joint offsets here, the DMU's
        # noise and quantisation in its emulator (with the model's noise figures)
        noise = SensorNoise()
        self.sensor_model = SensorModel(self.robot, terms, noise, seed=seed)
        self.devices = KrangCanDevices(
            self.config,
            seed=seed,
            imu_rate_noise_std_rad_s=noise.gyro_std_rad_s,
            imu_accel_noise_std_m_s2=noise.accel_std_m_s2,
            initial_joint_positions=dict(zip(self.robot.pose_joints, pose)),
        )
        self._command_joints()  # the modules clamp the pose to their limits
        self.k = 0  # physics steps taken
        # the modules' encoders read the plant's joints (its servos trail the modules' profiles)
        self._encoders_at = -1
        self._encoders: dict[str, float] = {}
        self.devices.read_joints_from(self._joint_encoders)
        self.lock = threading.Lock()
        self.sent_frames = 0
        self._warn_send = Throttled(self.get_logger().warning, 5.0)
        self.slips = 0
        self.max_lag = cfg.max_lag_s
        self.lockstep = cfg.lockstep
        self.lockstep_timeout = cfg.lockstep_timeout_s
        # the answer to a sample acts from this long after it in simulated time (the control path's
        # latency; at most one sample period less one physics step)
        self.lockstep_delay_steps = min(
            self.feedback_every - 1, max(0, round(cfg.lockstep_delay_s * self.rate))
        )
        self.answered = threading.Condition(self.lock)
        self.rpdo_seen = set()  # drives whose current frame came in since the last sample
        self.command_at = -math.inf  # wall time of the last command answering a new sample
        self.command_stamp = -math.inf  # the sample stamp it answered
        self.is_armed = False  # armed() at the last sample
        self.first_armed_at = None  # simulated time the lockstep first held the physics
        self.lockstep_misses = 0
        self.lockstep_wait_s = 0.0
        self.rpdo_ids = {w.codec.ids[amc_proto.RPDO_CURRENT] for w in self.devices.wheels.values()}
        # the devices read only the host's frames: the kernel drops the rest (above all the
        # echoes of our own feedback frames), and one thread reads every bus (bus_io)
        self.buses = {}
        for name in self.config.buses_in_use():
            bus = can.Bus(**self.config.buses[name].bus_kwargs())
            self.buses[name] = bus
            receive_only(bus, self.devices.host_ids(name))
        self.reader = (pump.reader if pump else BusReader)(
            self.buses, self.on_host_frame, self.on_bus_error
        )
        qos = topics.QOS
        self.clock_pub = self.create_publisher(Clock, names.CLOCK, qos[names.CLOCK])
        # read by the physics thread at each sample (take_latest), never a wake of the executor
        self.command_sub = self.create_subscription(
            JointState,
            names.relative(names.WHEEL_EFFORT_CMD),
            lambda msg: None,
            qos[names.WHEEL_EFFORT_CMD],
            callback_group=Polled(),
        )
        self.truth_pub = self.create_publisher(
            Float64MultiArray, names.private(names.GROUND_TRUTH), qos[names.GROUND_TRUTH]
        )
        self.diag_pub = self.create_publisher(
            DiagnosticArray, names.relative(names.DIAGNOSTICS), qos[names.DIAGNOSTICS]
        )
        self.truth_every = max(1, round(0.1 * self.rate))  # ground truth at 10 Hz of sim time
        self.create_timer(1.0, self.publish_diagnostics)
        self.running = True
        # When behind real time the physics loop does not sleep, and it would keep the GIL for the
        # interpreter's 5 ms switch interval at a time; the bus threads (nine of them then) got it
        # in turn and a wheel current command waited tens of simulated ms before it reached the
        # drive. 1 ms slices bound that to about a millisecond per waiting thread.
        sys.setswitchinterval(min(sys.getswitchinterval(), cfg.gil_switch_interval_s))
        self.silent_since = None
        silent = self.declare_parameter(
            'silent_devices',
            Parameter.Type.STRING_ARRAY,
            ParameterDescriptor(description=describe_parameters()[-1]),
        ).value
        if silent:
            self.silence(silent)
        self.add_on_set_parameters_callback(self.on_parameters)
        self.answer_due = None  # the step from which the answer to the last sample acts
        self.thread = None
        if pump is None:
            self.thread = threading.Thread(target=self.physics_loop, name='physics', daemon=True)
            self.thread.start()
        truth = self.sim.truth()
        self.get_logger().info(
            f'simulated Krang ({cfg.plant} plant, {self.true_robot}): truth {truth_file}, '
            f'sitting at q_base {truth.q_base:+.3f} rad, true balance '
            f'{truth.balance_pitch:+.3f} rad, {self.rate:.0f} Hz physics '
            f'at {self.factor:g}x real time{", lockstep" if self.lockstep else ""}, '
            f'buses {sorted(self.buses)}'
        )

    def on_host_frame(self, bus_name, msg):
        with self.lock:
            replies = self.devices.on_frame(bus_name, msg)
            if msg.arbitration_id in self.rpdo_ids:
                self.rpdo_seen.add(msg.arbitration_id)
                if self.rpdo_seen == self.rpdo_ids:
                    self.answered.notify()
        self.send(replies)

    def on_bus_error(self, bus_name, exc):
        self.get_logger().error(f'CAN receive on {bus_name} stopped: {exc}')

    def on_parameters(self, params):
        for param in params:
            if param.name == 'silent_devices':
                try:
                    self.silence(param.value or [])
                except ValueError as err:
                    return SetParametersResult(successful=False, reason=str(err))
        return SetParametersResult(successful=True)

    def silence(self, names):
        with self.lock:
            self.devices.set_silent(names)
            self.silent_since = self.sim.t if names else None
        if names:
            self.get_logger().warn(
                f'fault injection: {", ".join(names)} silent from t = {self.silent_since:.3f} s'
            )
        else:
            self.get_logger().info('fault injection: every device transmits again')
        self.publish_diagnostics()

    def armed(self):
        """Lockstep holds while wheel commands answering new samples come (within
        lockstep_timeout_s of wall time): a controller that repeats its last command under the old
        stamp (its IMU silent) is not answering, and the simulated time must go on for its
        stale-sensor check to fire."""
        if not self.lockstep:
            return False
        msg = take_latest(self.command_sub)
        if msg is not None:
            stamp = messages.stamp_seconds(msg.header.stamp)
            if stamp != self.command_stamp:  # answers a new sample (a repeat keeps the stamp)
                self.command_at = time.monotonic()
                self.command_stamp = stamp
        return time.monotonic() - self.command_at <= self.lockstep_timeout

    def wait_for_answer(self):
        """Lockstep: hold the physics until every drive's current frame answered the last sample
        (called with self.lock held; the wait releases it for the bus threads)."""
        self.is_armed = self.armed()
        if not self.is_armed:
            return
        if self.first_armed_at is None:
            self.first_armed_at = self.sim.t
        start = time.monotonic()
        if not self.answered.wait_for(
            lambda: self.rpdo_seen == self.rpdo_ids or not self.running, self.lockstep_timeout
        ):
            self.lockstep_misses += 1
        self.lockstep_wait_s += time.monotonic() - start

    def send(self, frames):
        for frame in frames:
            try:
                self.buses[frame.bus].send(frame.msg, timeout=0.01)
                self.sent_frames += 1
            except can.CanError as err:
                self._warn_send(f'send on {frame.bus} failed: {err}')

    def _joint_encoders(self) -> dict[str, float]:
        """The body joints as their encoders read them now (a module's poll, with self.lock
        held): the plant's joints through the sensor model, once per physics step."""
        if self._encoders_at != self.k:
            joints = self.sensor_model.joint_encoders(self.sim.joints)
            self._encoders = dict(zip(self.robot.pose_joints, joints.tolist()))
            self._encoders_at = self.k
        return self._encoders

    def _command_joints(self):
        joints = self.devices.joint_positions()
        self.sim.command_joints([joints[j] for j in self.robot.pose_joints])

    def _step(self):
        """One physics step, with self.lock held; the sensor frames of the step (at a sample)."""
        dt = 1.0 / self.rate
        k = self.k
        if self.devices.step(dt):  # the joints follow the modules, read only when one moved
            self._command_joints()
        currents = self.devices.wheel_currents()
        self.sim.command_currents(currents['JLWheel'], currents['JRWheel'])
        self.sim.step()
        self.k += 1
        if k % self.feedback_every:
            return []
        # the answer to this sample acts from this step on
        self.answer_due = k + 1 + self.lockstep_delay_steps
        self.rpdo_seen = set()
        return self.devices.sensor_frames(self.sim.motion(), self.sensor_model)

    def _after_step(self, frames):
        """Send the step's frames, then /clock (a node's timer that fires on this time finds the
        samples) and the ground truth when due; False once shut down."""
        self.send(frames)
        k = self.k - 1
        try:
            if self.publish_clock and k % self.clock_every == 0:
                clock = Clock()
                clock.clock.sec, nanosec = divmod(int(round(self.sim.t * 1e9)), 1_000_000_000)
                clock.clock.nanosec = nanosec
                self.clock_pub.publish(clock)
            if k % self.truth_every == 0:
                self.publish_truth()
        except RCLError:
            if self.context.ok():
                raise
            return False  # shut down by a signal under this thread: close() ends the rest
        return True

    def advance(self):
        """Composed (krang_cli.composed): step the physics up to the moment the answer to the
        next sample is due; the composition then delivers everything the sample caused."""
        while True:
            with self.lock:
                frames = self._step()
            self._after_step(frames)
            if self.k == self.answer_due:
                return

    def physics_loop(self):
        start = time.monotonic()
        paced_at = self.factor
        while self.running:
            with self.lock:
                if self.k == self.answer_due:
                    self.wait_for_answer()
                frames = self._step()
            if not self._after_step(frames):
                break
            factor = self.factor
            if factor <= 0 and self.lockstep and not self.is_armed:
                # unpaced lockstep without a control loop (yet): real time, not a free run of
                # simulated minutes before the nodes are up
                factor = 1.0
            if factor > 0:
                if factor != paced_at:  # a new schedule from here
                    paced_at, start = factor, time.monotonic() - self.sim.t / factor
                ahead = start + self.sim.t / factor - time.monotonic()
                if ahead > 0:
                    time.sleep(ahead)
                elif ahead < -self.max_lag:
                    # Starved of CPU: slow the simulated time down rather than catch up in a burst,
                    # which would let the robot fall for that long with no control in between.
                    start -= ahead
                    self.slips += 1

    def publish_truth(self):
        with self.lock:
            truth = self.sim.truth()
            values = [
                truth.t,
                truth.q_base,
                truth.x_m,
                truth.balance_pitch,
                *self.sim.motion().applied_current,
            ]
        msg = messages.labelled_array(values, GROUND_TRUTH_FIELDS, label='truth')
        self.truth_pub.publish(msg)

    def publish_diagnostics(self):
        with self.lock:
            truth = self.sim.truth()
            t, qb, bal = truth.t, truth.q_base, truth.balance_pitch
            silent, since = sorted(self.devices.silent), self.silent_since
            armed_at = self.first_armed_at
        values = {
            'plant': self.plant_name,
            'true_robot': self.true_robot,
            'q_base': f'{qb:+.4f}',
            'true_balance_pitch': f'{bal:+.4f}',
            'frames_sent': self.sent_frames,
            'real_time_slips': self.slips,
            'lockstep_wait_s': f'{self.lockstep_wait_s:.3f}',
            'lockstep_misses': self.lockstep_misses,
            # before it, the physics ran at real time without waiting for answers
            'lockstep_first_armed_s': 'no' if armed_at is None else f'{armed_at:.4f}',
        }
        if silent:
            values.update(silent_devices=', '.join(silent), silent_since_s=f'{since:.4f}')
        self.diag_pub.publish(
            messages.diagnostics(
                self.get_clock().now().to_msg(),
                'sim_krang',
                'warn' if silent else 'ok',
                f'simulated t = {t:.1f} s'
                + (f'; fault injection: {", ".join(silent)} silent' if silent else ''),
                values,
            )
        )

    def close(self):
        with self.lock:
            self.running = False
            self.answered.notify_all()
        if self.thread is not None:
            self.thread.join(timeout=2.0)
        self.reader.stop()
        for bus in self.buses.values():
            bus.shutdown()


def main(args=None):
    return run_node(SimKrangNode, args)


if __name__ == '__main__':
    sys.exit(main())
