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
from krang_core import names  # noqa: E402
from krang_ros import messages, topics  # noqa: E402

#: a burst, a stall of 20 samples (40 ms at 500 Hz: the sensor-data profile's 5 would drop 15)
#: and one of 45 (90 ms: topics.STEPPED's former 25 would drop 20)
BURSTS = (3, 20, 45)
#: the probe keeps every command the controller sends (best effort, as the topic, but deeper)
EVERY_COMMAND = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)


def spin_until(executor, condition, timeout=5.0):
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return condition()


class Rig:
    """adrc_controller in this process (step_on_imu, as config/krang_params.yaml) and a probe
    that publishes imu/data samples and keeps the stamps of every wheel command."""

    def __init__(self):
        self.controller = AdrcControllerNode()
        probe = rclpy.create_node('sample_probe')
        self.imu_pub = probe.create_publisher(Imu, names.IMU, topics.QOS[names.IMU])
        self.commands = []
        probe.create_subscription(
            JointState,
            names.WHEEL_EFFORT_CMD,
            lambda m: self.commands.append(messages.stamp_seconds(m.header.stamp)),
            EVERY_COMMAND,
        )
        self.probe_exec, self.control_exec = SingleThreadedExecutor(), SingleThreadedExecutor()
        self.probe_exec.add_node(probe)
        self.control_exec.add_node(self.controller)
        assert spin_until(self.probe_exec, lambda: self.imu_pub.get_subscription_count() > 0)
        assert spin_until(
            self.control_exec, lambda: self.controller.count_publishers(names.IMU) > 0
        ), 'the controller never saw the probe'

    def sample(self, t):
        msg = Imu()
        msg.header.stamp = messages.stamp(t)
        msg.orientation.w = 1.0
        msg.linear_acceleration.z = 9.81
        self.imu_pub.publish(msg)

    def answers(self, t):
        """How many wheel commands the probe got that answer the sample stamped `t`."""
        self.probe_exec.spin_once(timeout_sec=0.05)
        return sum(abs(c - t) < 1e-6 for c in self.commands)


@pytest.fixture
def rig():
    rclpy.init(args=['--ros-args', '-p', 'step_on_imu:=true'])
    try:
        yield Rig()
    finally:
        rclpy.try_shutdown()


@pytest.mark.parametrize('burst', BURSTS)
def test_a_burst_of_samples_is_stepped_whole_and_answered_once_for_the_newest(rig, burst):
    start = rig.controller.samples_stepped
    stamps = [1000.0 + 0.002 * k for k in range(burst)]
    for t in stamps:  # all in before the controller's executor runs again
        rig.sample(t)
    time.sleep(0.2)  # delivered to the controller's reader queue
    assert spin_until(rig.control_exec, lambda: rig.controller.samples_stepped > start)
    assert rig.controller.samples_stepped - start == burst
    assert rig.controller.samples_superseded == burst - 1
    assert spin_until(rig.probe_exec, lambda: rig.answers(stamps[-1]) == 1)
    assert [rig.answers(t) for t in stamps[:-1]] == [0] * (burst - 1)


def test_the_watch_timer_steps_on_a_waiting_sample_rather_than_repeat_the_last(rig):
    """After a stall the executor runs a due timer before a waiting subscription: the watch must
    step on the waiting sample, not repeat the last sample's stamp (sim_krang's lockstep would
    take the repeat for the next sample's answer)."""
    first = time.time()
    rig.sample(first)
    assert spin_until(rig.control_exec, lambda: rig.controller.samples_stepped == 1)
    time.sleep(0.2)  # the stall: well past the watch's three periods
    newer = time.time()
    rig.sample(newer)
    time.sleep(0.2)  # waiting in the controller's queue
    rig.controller.on_timer()  # the due timer runs first
    assert rig.controller.samples_stepped == 2
    assert spin_until(rig.probe_exec, lambda: rig.answers(newer) == 1)
    assert rig.answers(first) == 1


def test_a_malformed_message_last_in_a_burst_leaves_the_command_to_the_newest_valid_sample(rig):
    """Bytes on imu/data that are not an Imu are skipped, not stepped on; they neither take the
    command from the valid samples before them nor count as a superseded sample."""
    start = rig.controller.samples_stepped
    stamps = [2000.0 + 0.002 * k for k in range(3)]
    for t in stamps:
        rig.sample(t)
    rig.imu_pub.publish(b'\x00\x01\x00\x00' + b'\x07' * 12)  # cut short
    time.sleep(0.2)
    assert spin_until(rig.control_exec, lambda: rig.controller.samples_stepped > start)
    assert rig.controller.samples_stepped - start == 3
    assert rig.controller.samples_superseded == 2
    assert spin_until(rig.probe_exec, lambda: rig.answers(stamps[-1]) == 1)
    assert [rig.answers(t) for t in stamps[:-1]] == [0, 0]
