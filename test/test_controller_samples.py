"""adrc_controller steps the control law on every imu/data sample, but a sample that a newer one
supersedes before its step sends no wheel command: a burst of samples from the bridge costs no
late commands (README, "What a sample costs")."""

import time

import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402

from krang_adrc_controller.node import AdrcControllerNode  # noqa: E402
from krang_ros import messages, names, topics  # noqa: E402

BURST = 3
#: the probe keeps every command the controller sends (best effort, as the topic, but deeper)
EVERY_COMMAND = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)


def spin_until(executor, condition, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return condition()


def test_a_burst_of_samples_is_stepped_whole_and_answered_once_for_the_newest():
    rclpy.init(args=['--ros-args', '-p', 'step_on_imu:=true'])  # as config/krang_params.yaml
    try:
        controller = AdrcControllerNode()
        probe = rclpy.create_node('sample_probe')
        imu_pub = probe.create_publisher(Imu, names.IMU, topics.QOS[names.IMU])
        commands = []
        probe.create_subscription(
            JointState,
            names.WHEEL_EFFORT_CMD,
            lambda m: commands.append(messages.stamp_seconds(m.header.stamp)),
            EVERY_COMMAND,
        )
        probe_exec, control_exec = SingleThreadedExecutor(), SingleThreadedExecutor()
        probe_exec.add_node(probe)
        control_exec.add_node(controller)
        assert spin_until(probe_exec, lambda: imu_pub.get_subscription_count() > 0)
        assert spin_until(control_exec, lambda: controller.count_publishers(names.IMU) > 0), (
            'the controller never saw the probe'
        )
        start = controller.samples_stepped
        stamps = [1000.0 + 0.002 * k for k in range(BURST)]
        for t in stamps:  # all in before the controller's executor runs again
            msg = Imu()
            msg.header.stamp = messages.stamp(t)
            msg.orientation.w = 1.0
            msg.linear_acceleration.z = 9.81
            imu_pub.publish(msg)
        time.sleep(0.2)  # delivered to the controller's reader queue
        assert spin_until(control_exec, lambda: controller.samples_stepped > start)
        assert controller.samples_stepped - start == BURST
        assert controller.samples_superseded == BURST - 1
        answered = lambda t: any(abs(c - t) < 1e-6 for c in commands)  # noqa: E731
        assert spin_until(probe_exec, lambda: answered(stamps[-1]))
        assert not any(answered(t) for t in stamps[:-1])
    finally:
        rclpy.try_shutdown()


def test_the_watch_timer_steps_on_a_waiting_sample_rather_than_repeat_the_last():
    """After a stall the executor runs a due timer before a waiting subscription: the watch must
    step on the waiting sample, not repeat the last sample's stamp (sim_krang's lockstep would
    take the repeat for the next sample's answer)."""
    rclpy.init(args=['--ros-args', '-p', 'step_on_imu:=true'])
    try:
        controller = AdrcControllerNode()
        probe = rclpy.create_node('sample_probe')
        imu_pub = probe.create_publisher(Imu, names.IMU, topics.QOS[names.IMU])
        commands = []
        probe.create_subscription(
            JointState,
            names.WHEEL_EFFORT_CMD,
            lambda m: commands.append(messages.stamp_seconds(m.header.stamp)),
            EVERY_COMMAND,
        )
        probe_exec, control_exec = SingleThreadedExecutor(), SingleThreadedExecutor()
        probe_exec.add_node(probe)
        control_exec.add_node(controller)
        assert spin_until(probe_exec, lambda: imu_pub.get_subscription_count() > 0)
        assert spin_until(control_exec, lambda: controller.count_publishers(names.IMU) > 0)

        def sample(t):
            msg = Imu()
            msg.header.stamp = messages.stamp(t)
            msg.orientation.w = 1.0
            msg.linear_acceleration.z = 9.81
            imu_pub.publish(msg)

        sample(time.time())
        assert spin_until(control_exec, lambda: controller.samples_stepped == 1)
        time.sleep(0.2)  # the stall: well past the watch's three periods
        newer = time.time()
        sample(newer)
        time.sleep(0.2)  # waiting in the controller's queue
        controller.on_timer()  # the due timer runs first
        assert controller.samples_stepped == 2
        assert spin_until(probe_exec, lambda: len(commands) >= 2)
        probe_exec.spin_once(timeout_sec=0.1)
        assert commands[1] == pytest.approx(newer, abs=1e-6)
        assert len(set(round(c, 6) for c in commands)) == len(commands), commands
    finally:
        rclpy.try_shutdown()
