"""pose_server over ROS, as a process under a namespace: next_pose is refused unless the
controller balances and while a move is under way, and a move stops when the controller leaves
balance; every name moves with __ns."""

import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip('rclpy')
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from krang_model.robot import load_krang  # noqa: E402
from krang_ros import messages, names, topics  # noqa: E402

NS = '/robot7'


@pytest.fixture
def pose_server(tmp_path):
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


def call(node, context, client):
    assert client.wait_for_service(timeout_sec=30.0), 'next_pose not served under the namespace'
    future = client.call_async(Trigger.Request())
    executor = rclpy.executors.SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    executor.remove_node(node)
    return future.result()


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
