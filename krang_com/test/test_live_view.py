"""krang view: the Foxglove core without ROS, then the node fed by fake ROS publishers and read by
a WebSocket client speaking the Foxglove protocol (foxglove-sdk 0.30 negotiates the subprotocol
foxglove.sdk.v1, the successor of foxglove.websocket.v1)."""

import asyncio
import json
import struct
import threading
import time

import numpy as np
import pytest
import rclpy
import websockets
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from rclpy.executors import SingleThreadedExecutor
from sensor_msgs.msg import Imu, JointState

from krang_cli.main import build_parser
from krang_com_interfaces.msg import MassModel
from krang_model import com
from krang_model.robot import load_krang
from krang_core import names
from krang_core.pitch import pitch_quaternion
from krang_ros import messages, topics
from krang_ros.foxglove_view import LiveView
from krang_ros.spin import spin_until_shutdown
from krang_ros.view_node import LiveViewNode

SUBPROTOCOL = 'foxglove.sdk.v1'
CHANNELS = {
    '/transforms': 'foxglove.FrameTransforms',
    '/robot': 'foxglove.SceneUpdate',
    '/com': 'foxglove.SceneUpdate',
    '/com_live': 'krang.com_live',
    '/learning': 'krang.learning',
    '/mode': 'krang.mode',
}


def balanced_pose():
    robot = load_krang()
    joints = np.random.default_rng(3).uniform(robot.lower, robot.upper)
    return joints, float(com.balance_pitch(robot, joints[None], robot.nominal_beta)[0])


def test_view_command_is_registered():
    args = build_parser().parse_args(['view', '--port', '9001'])
    assert args.port == 9001 and args.host == '127.0.0.1'


def test_core_poses_the_robot_and_its_com():
    robot = load_krang()
    view = LiveView()
    assert view.transforms() is None and view.com_now() is None
    joints, q_star = balanced_pose()
    view.on_joints(dict(zip(robot.pose_joints, joints)) | {'JLWheel': 0.1, 'JRWheel': 0.1})
    view.on_imu(pitch_quaternion(q_star))
    children = {t.child for t in view.transforms()}
    assert set(view.frames.links) <= children
    q_base, estimated, nominal = view.com_now()
    assert q_base == pytest.approx(q_star, abs=1e-12)
    assert abs(nominal[0]) < 1e-9 and estimated == pytest.approx(nominal)
    shifted = robot.nominal_beta.copy()
    view.on_beta(shifted)
    assert view.beta_step is None  # the first estimate is no step
    shifted[1] += 0.5  # 0.5 kg m more along Base x
    view.on_beta(shifted)
    assert view.beta_step == pytest.approx(0.5)
    assert view.on_learned_com((0.002, 0.0, 0.5)) == {'pose': 1, 'x_com_mm': 2.0, 'beta_step': 0.5}
    scene = view.scene.encode()  # protobuf: link names appear as bytes
    assert all(name.encode() in scene for name in ('Base', 'LWheel', 'Spine', 'lGripper'))


async def read_session(port, publish, wanted, timeout=20.0):
    """Connect, check the advertised channels, subscribe to all, run `publish`, and collect the
    payloads by topic until every topic in `wanted` has arrived. The server drops a client that
    closes without flushing its reply to the close, which the client would otherwise await for
    its default close_timeout (10 s)."""
    async with websockets.connect(
        f'ws://127.0.0.1:{port}', subprotocols=[SUBPROTOCOL], close_timeout=0.5
    ) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        channels = {}
        while set(channels) != set(CHANNELS):
            msg = json.loads(await asyncio.wait_for(ws.recv(), timeout))
            if msg['op'] == 'advertise':
                channels.update({c['topic']: c for c in msg['channels']})
        assert {t: c['schemaName'] for t, c in channels.items()} == CHANNELS
        by_sub = dict(enumerate(channels))
        await ws.send(
            json.dumps(
                {
                    'op': 'subscribe',
                    'subscriptions': [
                        {'id': i, 'channelId': channels[t]['id']} for i, t in by_sub.items()
                    ],
                }
            )
        )
        await asyncio.sleep(0.3)
        await asyncio.get_running_loop().run_in_executor(None, publish)
        got = {}
        deadline = time.monotonic() + timeout
        while not wanted <= set(got) and time.monotonic() < deadline:
            frame = await asyncio.wait_for(ws.recv(), timeout)
            if isinstance(frame, bytes) and frame[0] == 1:  # opcode 1: message data
                sub, _ = struct.unpack('<IQ', frame[1:13])
                got.setdefault(by_sub[sub], []).append(frame[13:])
        return got


@pytest.mark.ros
def test_view_node_serves_the_robot_to_a_websocket_client():
    robot = load_krang()
    joints, q_star = balanced_pose()
    rclpy.init()
    node = LiveViewNode(port=0, rate_hz=50.0)
    fake = rclpy.create_node('fake_robot')
    qos = topics.QOS
    pub = {
        n: fake.create_publisher(t, n, qos[n])
        for n, t in (
            (names.JOINT_STATES, JointState),
            (names.BETA, MassModel),
            (names.COM, PointStamped),
            (names.DIAGNOSTICS, DiagnosticArray),
        )
    }
    pub[names.IMU] = fake.create_publisher(Imu, names.IMU, qos[names.IMU])
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    executor.add_node(fake)
    spinner = threading.Thread(target=spin_until_shutdown, args=(executor,), daemon=True)
    spinner.start()
    step = np.zeros(robot.n_beta)
    step[1] = 0.3

    def publish():
        stamp = fake.get_clock().now().to_msg()
        for beta in (robot.nominal_beta, robot.nominal_beta + step):
            pub[names.BETA].publish(messages.mass_model(stamp, robot.body_names, beta))
            time.sleep(0.3)
        point = PointStamped()
        point.header.frame_id = 'base_footprint'
        point.point.x, point.point.z = 0.0123, 0.5
        pub[names.COM].publish(point)
        pub[names.DIAGNOSTICS].publish(
            messages.diagnostics(stamp, 'adrc_controller', 'ok', '', {'mode': 'BALANCE_LO'})
        )
        for _ in range(20):
            pub[names.JOINT_STATES].publish(
                messages.joint_state(
                    stamp,
                    list(robot.pose_joints) + ['JLWheel', 'JRWheel'],
                    list(joints) + [0.0, 0.0],
                )
            )
            pub[names.IMU].publish(
                messages.imu(stamp, 'imu_link', q_star, 1e-6, (0, 0, 0), (0, 0, 9.81))
            )
            time.sleep(0.05)

    try:
        got = asyncio.run(read_session(node.port, publish, set(CHANNELS)))
    finally:
        rclpy.try_shutdown()  # ends the spin first (krang_ros.spin.spin_until_shutdown)
        spinner.join(5.0)
        executor.shutdown()
        node.close()
        node.destroy_node()
        fake.destroy_node()
    assert json.loads(got['/mode'][-1]) == {'mode': 'BALANCE_LO'}
    learning = json.loads(got['/learning'][0])
    assert learning == {
        'pose': 1,
        'x_com_mm': pytest.approx(12.3),
        'beta_step': pytest.approx(0.3),
    }
    live = json.loads(got['/com_live'][-1])
    assert live['q_base_rad'] == pytest.approx(q_star, abs=1e-9)
    assert abs(live['x_com_nominal_mm']) < 1e-6
    # the estimated beta moved the CoM by 0.3 kg m along Base x (the axle): sideways, not forward
    assert live['x_com_mm'] == pytest.approx(live['x_com_nominal_mm'], abs=1e-6)
    tree = got['/transforms'][-1]
    for frame in (b'odom', b'base_footprint', b'base_link', b'imu_link', b'Spine', b'rGripper'):
        assert frame in tree
    assert b'lGripper' in got['/robot'][0] and b'base_footprint' in got['/com'][-1]
