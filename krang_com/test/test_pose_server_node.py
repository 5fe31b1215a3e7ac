"""pose_server over ROS, as a process under a namespace: next_pose is refused unless the
controller balances and while a move is under way, and a move stops when the controller leaves
balance; a move holds its setpoint while the controller's balance_converged is false and goes on
when it is true; the move_to_next_pose action gives feedback while it moves, ends with the next
balanced pose, stops and holds where it is when cancelled, and says why when refused; an arm
fault (the bridge's latched /can_bridge/arm_fault) stops a move and holds it where it is, ends
its goal with the reason and makes next_pose refuse until it is cleared; every name moves with
__ns."""

import math
import subprocess
import sys
import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip('rclpy')
from action_msgs.msg import GoalStatus  # noqa: E402
from krang_com_interfaces.action import MoveToNextPose  # noqa: E402
from krang_com_interfaces.msg import ArmFault, BalancedPose, ControllerMode  # noqa: E402
from rclpy.action import ActionClient  # noqa: E402
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402
from std_msgs.msg import Bool  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from krang_adrc_controller.detector import BalancedPoint  # noqa: E402
from krang_model.com import balance_pitch  # noqa: E402
from krang_model.config import config_path  # noqa: E402
from krang_model.poses import load_poses, save_poses  # noqa: E402
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang  # noqa: E402
from krang_core import names  # noqa: E402
from krang_ros import messages, topics  # noqa: E402

NS = '/robot7'
#: the fixed poses the servers here move to: config/excitatory_poses.csv's first three, this
#: fraction of the way from the zero pose the tests start at (moves of about 3 s, not 15 s)
NEAR = 0.25


def near_poses(directory):
    """The fixed pose list of NEAR poses, written in `directory`; its path."""
    robot = load_krang()
    _, joints, _ = load_poses(config_path('excitatory_poses.csv'), KRANG_POSE_COLUMNS)
    joints = NEAR * joints[:3]
    pitch = balance_pitch(robot, joints, robot.nominal_beta)
    return save_poses(directory / 'near_poses.csv', pitch, joints, KRANG_POSE_COLUMNS)


@pytest.fixture
def pose_server(tmp_path):
    yield from start_pose_server(tmp_path, f'poses_file:={near_poses(tmp_path)}')


def start_pose_server(tmp_path, *parameters):
    extra = [a for p in parameters for a in ('-p', p)]
    proc = subprocess.Popen(
        [
            sys.executable,
            '-m',
            'krang_ros.entry',
            'pose_server',
            '--ros-args',
            '-r',
            f'__ns:={NS}',
            '-p',
            'selection:=fixed',
            *extra,
        ],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    context = rclpy.Context()
    rclpy.init(context=context)
    node = Node('pose_server_probe', namespace=NS, context=context)
    yield proc, node, context
    node.destroy_node()
    rclpy.try_shutdown(context=context)
    proc.send_signal(2)
    out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0 and 'Traceback' not in out, out[-2000:]


def spin(node, context, seconds):
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    executor.remove_node(node)


def call(node, context, client, attempts=3):
    """One next_pose answer. DDS drops a service answer whose reader the server has not matched
    yet, which can happen to the first call after discovery; that call is asked again (the
    first calls here are refusals, which change nothing on the server)."""
    assert client.wait_for_service(timeout_sec=30.0), 'next_pose not served under the namespace'
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        for _ in range(attempts):
            future = client.call_async(Trigger.Request())
            executor.spin_until_future_complete(future, timeout_sec=5.0)
            if future.done():
                return future.result()
            client.remove_pending_request(future)
    finally:
        executor.remove_node(node)
    raise AssertionError(f'no answer from next_pose in {attempts} calls')


def mode_publisher(node):
    """A fake controller's latched mode topic: publish(name)."""
    pub = node.create_publisher(ControllerMode, names.relative(names.MODE), topics.LATCHED)
    return lambda name: pub.publish(
        messages.controller_mode(node.get_clock().now().to_msg(), name)
    )


def test_next_pose_waits_for_the_controller(pose_server):
    proc, node, context = pose_server
    commands = []
    node.create_subscription(
        JointState, names.relative(names.JOINT_POSITION_CMD), commands.append, 10
    )
    mode = mode_publisher(node)
    client = node.create_client(Trigger, f'{NS}/pose_server/next_pose')  # moved with __ns

    reply = call(node, context, client)  # no controller yet
    assert not reply.success and 'not balancing' in reply.message
    mode('sit')
    spin(node, context, 0.5)
    reply = call(node, context, client)
    assert not reply.success and 'mode: sit' in reply.message

    joint_states = node.create_publisher(JointState, names.relative(names.JOINT_STATES), 10)
    joint_states.publish(
        messages.joint_state(node.get_clock().now().to_msg(), load_krang().pose_joints, [0.0] * 16)
    )
    mode('balance')
    spin(node, context, 0.5)
    reply = call(node, context, client)
    assert reply.success, reply.message
    spin(node, context, 1.0)
    assert len(commands) >= 5, 'the move did not stream'
    reply = call(node, context, client)
    assert not reply.success and 'under way' in reply.message
    mode('safe_stop')
    spin(node, context, 0.5)
    n = len(commands)
    spin(node, context, 1.0)
    assert len(commands) == n, 'the move went on after the controller left balance'


@pytest.fixture
def patient_pose_server(tmp_path):
    yield from start_pose_server(
        tmp_path, 'max_pause_s:=60.0', f'poses_file:={near_poses(tmp_path)}'
    )


def test_a_move_holds_while_the_balance_estimate_is_unconverged(patient_pose_server):
    proc, node, context = patient_pose_server
    commands, targets = [], []
    node.create_subscription(
        JointState, names.relative(names.JOINT_POSITION_CMD), commands.append, 100
    )
    node.create_subscription(
        JointState, f'{NS}/pose_server/target', targets.append, topics.QOS[names.POSE_TARGET]
    )
    mode = mode_publisher(node)
    converged = node.create_publisher(
        Bool, names.relative(names.BALANCE_CONVERGED), topics.LATCHED
    )
    joint_states = node.create_publisher(JointState, names.relative(names.JOINT_STATES), 10)
    client = node.create_client(Trigger, f'{NS}/pose_server/next_pose')
    assert client.wait_for_service(timeout_sec=30.0)
    mode('balance')
    converged.publish(Bool(data=False))  # a fake controller: the estimate is not settled
    spin(node, context, 1.0)
    joint_states.publish(
        messages.joint_state(node.get_clock().now().to_msg(), load_krang().pose_joints, [0.0] * 16)
    )
    spin(node, context, 0.5)
    reply = call(node, context, client)
    assert reply.success, reply.message
    spin(node, context, 1.5)
    held = np.array([m.position for m in commands])
    assert len(held) >= 10, 'the move did not stream'
    np.testing.assert_array_equal(held, np.zeros_like(held))  # the start, held
    assert targets and np.any(np.array(targets[-1].position) != 0.0)
    converged.publish(Bool(data=True))
    goal = np.array(targets[-1].position)
    end = time.monotonic() + 40.0
    while time.monotonic() < end and not np.allclose(commands[-1].position, goal):
        spin(node, context, 0.5)
    assert np.allclose(commands[-1].position, goal), 'the move did not finish'
    spin(node, context, 0.3)
    reply = call(node, context, client)  # the move has ended: the next one is accepted
    assert reply.success and '1 pause(s)' in reply.message, reply.message


class Probe:
    """A fake controller and IMU beside the pose server, and a client of its move action."""

    def __init__(self, node, context):
        self.node, self.context = node, context
        self.executor = rclpy.executors.SingleThreadedExecutor(context=context)
        self.executor.add_node(node)
        self.commands, self.targets, self.feedback = [], [], []
        node.create_subscription(
            JointState, names.relative(names.JOINT_POSITION_CMD), self.commands.append, 100
        )
        node.create_subscription(
            JointState, f'{NS}/pose_server/target', self.targets.append, topics.LATCHED
        )
        self.mode = mode_publisher(node)
        self.imu = node.create_publisher(Imu, names.relative(names.IMU), topics.QOS[names.IMU])
        self.poses = node.create_publisher(
            BalancedPose, names.relative(names.BALANCED_POSE), topics.QOS[names.BALANCED_POSE]
        )
        self.joint_states = node.create_publisher(
            JointState, names.relative(names.JOINT_STATES), 10
        )
        self.action = ActionClient(node, MoveToNextPose, f'{NS}/pose_server/move_to_next_pose')
        self.next_pose = node.create_client(Trigger, f'{NS}/pose_server/next_pose')

    def spin_until(self, condition, timeout, what):
        """Spin (publishing /imu/data at a pitch of PITCH) until `condition()`."""
        end = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < end, f'timed out waiting for {what}'
            stamp = self.node.get_clock().now().to_msg()
            self.imu.publish(messages.imu(stamp, 'imu', PITCH, 1e-6, (0, 0, 0), (0, 0, 9.8)))
            self.executor.spin_once(timeout_sec=0.02)

    def pause(self, seconds):
        end = time.monotonic() + seconds
        self.spin_until(lambda: time.monotonic() > end, seconds + 1.0, 'the time')

    def send(self):
        """A goal, accepted (as every goal is: a refused one ends at once, aborted): (goal
        handle, its feedback list, the future of its result)."""
        assert self.action.wait_for_server(timeout_sec=30.0), 'move_to_next_pose not served'
        feedback = []
        future = self.action.send_goal_async(
            MoveToNextPose.Goal(), feedback_callback=lambda m: feedback.append(m.feedback)
        )
        self.spin_until(future.done, 10.0, 'the goal accepted')
        handle = future.result()
        assert handle.accepted
        return handle, feedback, handle.get_result_async()

    def result(self, result, timeout):
        self.spin_until(result.done, timeout, 'the result')
        return result.result().status, result.result().result


PITCH = -1.55  # the fake IMU's pitch [rad]


def test_move_to_next_pose_action(pose_server):
    """Refused with its reason; feedback while moving; the next balanced pose after the move
    ends it, with the target; next_pose is refused meanwhile; cancel stops the move and holds
    the pose where it stopped."""
    _, node, context = pose_server
    probe = Probe(node, context)
    robot = load_krang()

    _, _, result = probe.send()  # no controller yet: refused, with why
    status, res = probe.result(result, 10.0)
    assert status == GoalStatus.STATUS_ABORTED and not res.success
    assert 'not balancing' in res.message, res.message

    probe.joint_states.publish(
        messages.joint_state(node.get_clock().now().to_msg(), robot.pose_joints, [0.0] * 16)
    )
    probe.mode('balance')
    probe.pause(0.5)
    _, feedback, result = probe.send()
    probe.spin_until(lambda: len(probe.targets) > 0, 10.0, 'the target')
    target = np.array(probe.targets[-1].position)
    probe.spin_until(lambda: feedback and feedback[-1].progress > 0.2, 10.0, 'progress')
    future = probe.next_pose.call_async(Trigger.Request())
    probe.spin_until(future.done, 10.0, 'the next_pose answer')
    assert not future.result().success and 'under way' in future.result().message
    probe.spin_until(lambda: feedback[-1].progress == 1.0, 30.0, 'the move to end')
    progress = [f.progress for f in feedback]
    assert progress == sorted(progress) and 0.0 <= progress[0] < 0.2, progress
    assert not any(f.paused_for_balance for f in feedback)
    assert math.isnan(feedback[-1].expected_gain)  # the fixed list predicts no gain
    assert feedback[-1].base_pitch == pytest.approx(PITCH, abs=1e-6)
    assert not result.done(), 'the goal ended before its balanced pose'
    point = BalancedPoint(
        t=1.0, q_base=-1.5432, joints=target, q_base_std=0.001, n_samples=45, window_s=1.5
    )
    probe.poses.publish(
        messages.balanced_pose(node.get_clock().now().to_msg(), robot.pose_joints, point)
    )
    status, res = probe.result(result, 10.0)
    assert status == GoalStatus.STATUS_SUCCEEDED and res.success, res.message
    assert res.balanced_pose.base_pitch == -1.5432
    np.testing.assert_allclose(res.target, target)

    handle, feedback, result = probe.send()
    probe.spin_until(lambda: feedback and feedback[-1].progress > 0.1, 10.0, 'progress')
    cancel = handle.cancel_goal_async()
    probe.spin_until(cancel.done, 10.0, 'the cancel answer')
    assert len(cancel.result().goals_canceling) == 1
    status, res = probe.result(result, 10.0)
    assert status == GoalStatus.STATUS_CANCELED and not res.success
    assert res.message.startswith('cancelled: the move stopped'), res.message
    probe.pause(0.3)  # the held setpoint's command, which can come after the result
    n = len(probe.commands)
    probe.pause(1.0)
    assert len(probe.commands) == n, 'the move went on after its cancel'
    held = np.array(probe.commands[-1].position)
    np.testing.assert_array_equal(probe.targets[-1].position, held)  # the held pose: the target
    assert 0.05 < np.max(np.abs(held)) and not np.allclose(held, res.target)


def test_an_arm_fault_stops_the_move_and_refuses_the_next_until_cleared(pose_server):
    """A fake bridge latches an arm fault during a move: the move stops and holds where it is
    (the other joints commanded at that setpoint once more), the goal ends with the reason, and
    next_pose and new goals are refused with it until the fault is cleared."""
    _, node, context = pose_server
    probe = Probe(node, context)
    robot = load_krang()
    arm = node.create_publisher(ArmFault, names.relative(names.ARM_FAULT), topics.LATCHED)
    reason = 'arm module powercube/LJ2/can0:5 (LJ2) not answering'
    assert probe.action.wait_for_server(timeout_sec=30.0), 'move_to_next_pose not served'
    probe.pause(0.5)  # the server's readers matched
    probe.joint_states.publish(
        messages.joint_state(node.get_clock().now().to_msg(), robot.pose_joints, [0.0] * 16)
    )
    probe.mode('balance')
    arm.publish(messages.arm_fault(node.get_clock().now().to_msg(), '', []))
    probe.pause(0.5)
    _, feedback, result = probe.send()
    probe.spin_until(
        lambda: result.done() or (feedback and feedback[-1].progress > 0.1), 10.0, 'progress'
    )
    assert not result.done(), result.result().result.message
    arm.publish(messages.arm_fault(node.get_clock().now().to_msg(), reason, ['LJ2']))
    status, res = probe.result(result, 10.0)
    assert status == GoalStatus.STATUS_ABORTED and not res.success
    assert reason in res.message and names.BRIDGE_RECOVER in res.message, res.message
    assert 'stopped at' in res.message and 'holding there' in res.message, res.message
    probe.pause(0.3)  # the held setpoint's command, which can come after the result
    n = len(probe.commands)
    probe.pause(1.0)
    assert len(probe.commands) == n, 'the move went on after the arm fault'
    held = np.array(probe.commands[-1].position)
    np.testing.assert_array_equal(probe.targets[-1].position, held)  # the held pose: the target
    assert 0.0 < np.max(np.abs(held)) and not np.allclose(held, res.target)

    future = probe.next_pose.call_async(Trigger.Request())
    probe.spin_until(future.done, 10.0, 'the next_pose answer')
    refused = future.result()
    assert not refused.success and reason in refused.message, refused.message
    assert f'recover with {names.BRIDGE_RECOVER}' in refused.message
    _, _, result = probe.send()
    status, res = probe.result(result, 10.0)
    assert status == GoalStatus.STATUS_ABORTED and reason in res.message, res.message
    assert len(probe.commands) == n, 'a refused move commanded the joints'

    arm.publish(messages.arm_fault(node.get_clock().now().to_msg(), '', []))
    probe.pause(0.5)
    future = probe.next_pose.call_async(Trigger.Request())
    probe.spin_until(future.done, 10.0, 'the next_pose answer')
    assert future.result().success, future.result().message
