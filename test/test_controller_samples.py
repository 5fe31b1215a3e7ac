"""adrc_controller steps the control law on every imu/data sample, but a sample that a newer one
supersedes before its step sends no wheel command: a burst of samples from the bridge costs no
late commands (README, "What a sample costs")."""

import time

import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402

from krang_adrc_controller.node import AdrcControllerNode  # noqa: E402
from krang_ros import messages, names, topics  # noqa: E402

BURST = 3


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
            topics.QOS[names.WHEEL_EFFORT_CMD],
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
        assert spin_until(probe_exec, lambda: commands)
        assert commands[0] == pytest.approx(stamps[-1], abs=1e-6)
        assert all(abs(c - t) > 1e-6 for c in commands for t in stamps[:-1])
    finally:
        rclpy.try_shutdown()
