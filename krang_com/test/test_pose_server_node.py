"""pose_server over ROS, as a process under a namespace: next_pose is refused unless the
controller balances and while a move is under way, and a move stops when the controller leaves
balance; a move holds its setpoint while the controller's balance_converged is false and goes on
when it is true; every name moves with __ns."""

import subprocess
import sys
import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip('rclpy')
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Bool, String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from krang_model.robot import load_krang  # noqa: E402
from krang_core import names  # noqa: E402
from krang_ros import messages, topics  # noqa: E402

NS = '/robot7'


@pytest.fixture
def pose_server(tmp_path):
    yield from start_pose_server(tmp_path)


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


def test_next_pose_waits_for_the_controller(pose_server):
    proc, node, context = pose_server
    commands = []
    node.create_subscription(
        JointState, names.relative(names.JOINT_POSITION_CMD), commands.append, 10
    )
    mode = node.create_publisher(String, names.relative(names.MODE), topics.LATCHED)
    client = node.create_client(Trigger, f'{NS}/pose_server/next_pose')  # moved with __ns

    reply = call(node, context, client)  # no controller yet
    assert not reply.success and 'not balancing' in reply.message
    mode.publish(String(data='sit'))
    spin(node, context, 0.5)
    reply = call(node, context, client)
    assert not reply.success and 'mode: sit' in reply.message

    joint_states = node.create_publisher(JointState, names.relative(names.JOINT_STATES), 10)
    joint_states.publish(
        messages.joint_state(node.get_clock().now().to_msg(), load_krang().pose_joints, [0.0] * 16)
    )
    mode.publish(String(data='balance'))
    spin(node, context, 0.5)
    reply = call(node, context, client)
    assert reply.success, reply.message
    spin(node, context, 1.0)
    assert len(commands) >= 5, 'the move did not stream'
    reply = call(node, context, client)
    assert not reply.success and 'under way' in reply.message
    mode.publish(String(data='safe_stop'))
    spin(node, context, 0.5)
    n = len(commands)
    spin(node, context, 1.0)
    assert len(commands) == n, 'the move went on after the controller left balance'


@pytest.fixture
def patient_pose_server(tmp_path):
    yield from start_pose_server(tmp_path, 'max_pause_s:=60.0')


def test_a_move_holds_while_the_balance_estimate_is_unconverged(patient_pose_server):
    proc, node, context = patient_pose_server
    commands, targets = [], []
    node.create_subscription(
        JointState, names.relative(names.JOINT_POSITION_CMD), commands.append, 100
    )
    node.create_subscription(
        JointState, f'{NS}/pose_server/target', targets.append, topics.QOS[names.POSE_TARGET]
    )
    mode = node.create_publisher(String, names.relative(names.MODE), topics.LATCHED)
    converged = node.create_publisher(
        Bool, names.relative(names.BALANCE_CONVERGED), topics.LATCHED
    )
    joint_states = node.create_publisher(JointState, names.relative(names.JOINT_STATES), 10)
    client = node.create_client(Trigger, f'{NS}/pose_server/next_pose')
    assert client.wait_for_service(timeout_sec=30.0)
    mode.publish(String(data='balance'))
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
