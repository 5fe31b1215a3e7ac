"""adrc_controller: the balance controller on ROS topics (thin shell over controller.BalanceController).

Control runs from the latest /imu/data and /joint_states, either on a timer at `rate_hz` (the node's
clock: wall time, or /clock with use_sim_time) or, with `step_on_imu`, once per /imu/data sample (the
2018 kore loop also waited for each IMU message). Stepping on the sample removes the phase lag between
two free-running loops at the same rate: the timer fired just before the bridge's next sample arrived
and so used a sample one period old (measured over DDS at 100 Hz: median 10 ms, p90 25 ms of extra
sample age). The timer then only watches: if no sample has driven the loop for two periods it steps
anyway, so stale data still end in a safe stop. If either input is older than `stale_timeout_s`, the
controller is told the data are stale and commands zero torque (safe stop) until it is re-enabled.
"""
import ctypes
import sys

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool

from krang_model.beta import load_beta
from krang_model.robot import load_krang
from krang_ros import messages, names, params, topics
from krang_ros.names import WHEEL_JOINTS as WHEELS
from krang_ros.spin import run_node

from .controller import BalanceController, ControllerConfig, ControlSample


class AdrcControllerNode(Node):
    def __init__(self):
        super().__init__('adrc_controller')
        self.robot = load_krang()
        # every ControllerConfig leaf is a dotted ROS parameter (adrc.eso.omega_o; controller.yaml)
        self.config = params.declare(self, ControllerConfig)
        self.stale_timeout = self.config.safety.stale_timeout_s
        self.step_on_imu = bool(self.declare_parameter('step_on_imu', False).value)
        beta_file = self.declare_parameter('initial_beta', '').value
        beta = load_beta(beta_file, self.robot) if beta_file else self.robot.nominal_beta
        self.controller = BalanceController(self.robot, beta, self.config)
        self.imu = None
        self.joint_state = None
        self.target = None
        self.mode = None
        self.effort_pub = self.create_publisher(Float64MultiArray, topics.WHEEL_EFFORT_CMD, topics.QOS[topics.WHEEL_EFFORT_CMD])
        self.pose_pub = self.create_publisher(JointState, topics.BALANCED_POSE, topics.QOS[topics.BALANCED_POSE])
        self.diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, topics.QOS[topics.DIAGNOSTICS])
        # Control acts on the newest sample only: after a stall, a queue of older samples (sensor QoS keeps
        # 5, /joint_states 10) would be worked off one control step each, every one of them late.
        latest = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.create_subscription(Imu, topics.IMU, self.on_imu, latest)
        self.create_subscription(JointState, topics.JOINT_STATES, self.on_joint_states, latest)
        self.create_subscription(Float64MultiArray, topics.BETA, self.on_beta, topics.QOS[topics.BETA])
        self.create_subscription(JointState, topics.POSE_TARGET, self.on_target, topics.QOS[topics.POSE_TARGET])
        self.create_service(SetBool, names.ENABLE, self.on_enable)
        self.period = 1.0 / self.config.rate_hz
        self.last_step = None
        self.last_sample_t = None
        self.create_timer(self.period, self.on_timer)
        self.create_timer(1.0, self.publish_diagnostics)
        self.last_output = None
        self.get_logger().info(f'balancing at {self.config.rate_hz:.0f} Hz '
                               f'({"on each /imu/data sample" if self.step_on_imu else "on a timer"}), stale '
                               f'timeout {self.stale_timeout} s, initial beta {beta_file or "nominal (URDF)"}')

    def now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def on_imu(self, msg):
        q = msg.orientation
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        self.imu = (self.now(), messages.pitch_from_quaternion(q.x, q.y, q.z, q.w), msg.angular_velocity.y, stamp)
        if self.step_on_imu:
            self.on_tick(sample_t=stamp)

    def on_timer(self):
        if self.step_on_imu and self.last_step is not None and self.now() - self.last_step < 2.0 * self.period:
            return
        self.on_tick()

    def on_joint_states(self, msg):
        joints = messages.joints_from_state(msg, self.robot.pose_joints)
        wheels = messages.joints_from_state(msg, WHEELS)
        if joints is None or wheels is None:
            self.get_logger().warn('joint_states without all body joints and wheels; ignored', throttle_duration_sec=5)
            return
        rates = messages.velocities_from_state(msg, WHEELS)
        self.joint_state = (self.now(), joints, wheels, rates if rates is not None else np.zeros(2))

    def on_target(self, msg):
        self.target = messages.joints_from_state(msg, self.robot.pose_joints)

    def on_beta(self, msg):
        beta = messages.array_values(msg, self.robot.n_beta)
        if beta is None:
            self.get_logger().error(f'rejected a beta of {len(msg.data)} values or with NaN/inf')
            return
        self.controller.set_beta(beta)
        self.get_logger().info(f'new beta (total mass {beta[0::4].sum():.2f} kg)')

    def sensors_stale(self):
        now = self.now()
        # now == 0: on use_sim_time before the first /clock (its discovery can lag the data topics by
        # seconds under load): every age would read 0, and the first /clock would make them all stale.
        return (now <= 0.0 or self.imu is None or self.joint_state is None or now - self.imu[0] > self.stale_timeout
                or now - self.joint_state[0] > self.stale_timeout)

    def on_enable(self, request, response):
        if request.data and self.sensors_stale():
            response.success = False
            response.message = 'not enabled: no fresh /imu/data and /joint_states yet (is can_bridge up?)'
            self.get_logger().warn(response.message)
            return response
        self.controller.set_enabled(bool(request.data))
        response.success = True
        response.message = 'enabled' if request.data else 'disabled: wheels stopped'
        self.get_logger().info(response.message)
        return response

    def on_tick(self, sample_t=None):
        """One control step. `sample_t`: the time of the IMU sample that triggered it (its header stamp,
        the bridge's clock when it published), so the ESO integrates over the samples' own spacing."""
        now = self.now()
        self.last_step = now
        stale = self.sensors_stale()
        if sample_t is None:
            sample_t = now
        if self.last_sample_t is not None and sample_t <= self.last_sample_t:   # a repeated or older stamp
            sample_t = max(now, self.last_sample_t + self.period)
        self.last_sample_t = sample_t
        if self.imu is None or self.joint_state is None:
            sample = ControlSample(sample_t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, np.zeros(len(self.robot.pose_joints)), False)
        else:
            _, q_base, pitch_rate, _ = self.imu
            _, joints, wheels, rates = self.joint_state
            moving = self.target is not None and bool(np.any(np.abs(self.target - joints) > 0.01))
            sample = ControlSample(sample_t, q_base, pitch_rate, wheels[0], wheels[1], rates[0], rates[1], joints,
                                   moving)
        out = self.controller.step(sample, stale=stale)
        self.last_output = out
        effort = Float64MultiArray()
        effort.data = [float(out.torque_left), float(out.torque_right)]
        self.effort_pub.publish(effort)
        for event in out.events:
            self.get_logger().info(event)
        if out.mode != self.mode:
            self.get_logger().info(f'mode {self.mode} -> {out.mode}')
            self.mode = out.mode
            self.publish_diagnostics()          # a mode change is reported at once, not at the next 1 Hz report
        if out.balanced_point is not None:
            point = out.balanced_point
            names = list(self.robot.pose_joints) + [messages.BASE_PITCH]
            values = list(point.joints) + [point.q_base]
            self.pose_pub.publish(messages.joint_state(self.get_clock().now().to_msg(), names, values))
            self.get_logger().info(f'balanced pose detected: q_base {point.q_base:+.4f} rad')

    def publish_diagnostics(self):
        out = self.last_output
        level = 'ok' if out is not None and out.mode != 'safe_stop' else 'warn'
        values = {} if out is None else {'mode': out.mode, 'theta_rad': f'{out.theta:+.4f}', 'x_m': f'{out.x:+.3f}',
                                         'f_hat_theta': f'{out.f_hat_theta:+.3f}', 'f_hat_x': f'{out.f_hat_x:+.3f}',
                                         'x_ref_m': f'{out.x_ref:+.3f}', 'balance_trim_rad': f'{out.balance_trim:+.4f}'}
        self.diag_pub.publish(messages.diagnostics(self.get_clock().now().to_msg(), 'adrc_controller', level,
                                                   f'mode {out.mode if out else "starting"}', values))


def single_thread_blas() -> int:
    """Limit the OpenBLAS libraries loaded in this process (numpy's and scipy's) to one thread.

    Why: the LQR(q) redesign (python-control -> scipy -> LAPACK) on 4x4 matrices gains nothing from
    threads, but on a loaded machine OpenBLAS's thread pool turned a 1 ms design into 20-65 ms
    (measured on the shared 2-core dev box), stalling the 500 Hz loop. Same effect as
    OPENBLAS_NUM_THREADS=1 set before numpy is imported; process-wide, so the node's process sets
    it, not the controller. Linux only; returns the number of libraries changed (0 when none)."""
    try:
        with open('/proc/self/maps') as f:
            libs = sorted({line.split()[-1] for line in f
                           if 'openblas' in line.lower() and '/' in line})
    except OSError:
        return 0
    changed = 0
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in ('scipy_openblas_set_num_threads64_', 'scipy_openblas_set_num_threads',
                     'openblas_set_num_threads64_', 'openblas_set_num_threads'):
            fn = getattr(lib, name, None)
            if fn is not None:
                fn(1)
                changed += 1
                break
    return changed


def main(args=None):
    single_thread_blas()
    return run_node(AdrcControllerNode, args)


if __name__ == '__main__':
    sys.exit(main())
