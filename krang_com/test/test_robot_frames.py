"""REP-103/105/145 frames: the published IMU orientation, the URDF's base_link/imu_link and the tf
tree of krang_ros.robot_frames agree with the model and with physics (no ROS graph needed)."""

import math
import time
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import numpy as np
import pinocchio as pin
import pytest
import rclpy
from builtin_interfaces.msg import Time
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu
from std_msgs.msg import String

from krang_can_bridge.imu_filter import sensor_vectors
from krang_can_bridge.node import CanBridgeNode
from krang_model import com
from krang_core.pitch import pitch_from_quaternion, pitch_from_specific_force, pitch_quaternion
from krang_model.robot import KRANG_URDF, load_krang
from krang_ros.robot_frames import (
    BASE_FOOTPRINT,
    BASE_LINK,
    IMU_LINK,
    ODOM,
    RobotFrames,
    matrix_from_quaternion,
)
from krang_ros.state_publisher import ROBOT_DESCRIPTION, StatePublisherNode
from krang_ros.topics import LATCHED

G = 9.81
SIT = -1.76
MOUNT = -math.pi / 4


def rot_z(a):
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def world_placements(transforms):
    """Every frame's (R, p) in odom, composed from parent -> child edges (each child once)."""
    by_child = {t.child: t for t in transforms}
    assert len(by_child) == len(transforms), 'a frame with two parents'
    out = {ODOM: (np.eye(3), np.zeros(3))}

    def place(name):
        if name not in out:
            t = by_child[name]
            r, p = place(t.parent)
            out[name] = (r @ t.rotation, p + r @ t.translation)
        return out[name]

    for name in by_child:
        place(name)
    return out


def published_tree(frames, q_base, joints, wheels=(0.0, 0.0)):
    robot = load_krang()
    frames.set_joints(dict(zip(robot.pose_joints, joints)))
    orientation = pitch_quaternion(q_base)
    return world_placements(
        frames.static_transforms()
        + frames.joint_transforms()
        + frames.base_transforms(orientation, *wheels)
    )


@pytest.fixture(scope='module')
def poses():
    robot = load_krang()
    rng = np.random.default_rng(7)
    return rng.uniform(robot.lower, robot.upper, (6, len(robot.lower)))


def test_urdf_has_rep103_frames_without_mass():
    root = ET.parse(KRANG_URDF).getroot()
    for link in (BASE_LINK, IMU_LINK):
        assert root.find(f"link[@name='{link}']") is not None
        assert root.find(f"link[@name='{link}']/inertial") is None
    kinds = {
        j.find('child').get('link'): (j.get('type'), j.find('parent').get('link'))
        for j in root.findall('joint')
    }
    assert kinds[BASE_LINK] == ('fixed', 'Base') and kinds[IMU_LINK] == ('fixed', BASE_LINK)


def test_tree_reaches_every_link_once_from_odom():
    frames = RobotFrames()
    tree = published_tree(frames, -0.8, np.zeros(len(load_krang().pose_joints)))
    assert set(tree) == set(frames.links) | {ODOM, BASE_FOOTPRINT}


@pytest.mark.parametrize('q_base', [SIT, -1.34, -0.6, 0.0, 0.4])
def test_accelerometer_sees_gravity_of_the_published_orientation(q_base):
    """(a) The bridge's published specific force of a robot at rest equals the published
    orientation's inverse applied to (0, 0, g), in imu_link."""
    force, rates = sensor_vectors(q_base, 0.0, MOUNT, gravity=G)
    fake = SimpleNamespace(
        config=SimpleNamespace(imu=SimpleNamespace(mount_angle_rad=MOUNT, frame_id=IMU_LINK))
    )
    sample = SimpleNamespace(
        rates=rates, specific_force=force, pitch=q_base, pitch_variance=1e-6, pitch_rate=0.0
    )
    msg = deserialize_message(CanBridgeNode._imu_message(fake, sample, Time()), Imu)
    o, a = msg.orientation, msg.linear_acceleration
    expected = matrix_from_quaternion(o.x, o.y, o.z, o.w).T @ np.array([0.0, 0.0, G])
    np.testing.assert_allclose([a.x, a.y, a.z], expected, atol=1e-9)
    assert msg.header.frame_id == IMU_LINK
    # the controller reads the pitch back from the specific force alone (the detector's mean)
    assert pitch_from_specific_force(a.x, a.y, a.z, G) == pytest.approx(q_base, abs=1e-12)
    # not gravity alone (an accelerating robot, a driver that leaves the field zero): not measured
    assert math.isnan(pitch_from_specific_force(0.0, 0.0, 0.0, G))
    assert math.isnan(pitch_from_specific_force(1.1 * a.x, a.y, 1.1 * a.z, G))


def test_com_is_over_the_axle_at_the_balance_pitch(poses):
    """(b) At the model's balance pitch the whole-robot CoM (URDF inertials placed by the
    published tree) is vertically above the axle line (no offset along the heading, odom x at yaw
    0; arms may shift it sideways along the axle) and equals krang_model's com_frame0."""
    robot = load_krang()
    root = ET.parse(KRANG_URDF).getroot()
    inertials = [
        (
            link.get('name'),
            float(link.find('inertial/mass').get('value')),
            np.array([float(v) for v in link.find('inertial/origin').get('xyz').split()]),
        )
        for link in root.findall('link')
        if link.find('inertial') is not None
    ]
    frames = RobotFrames()
    pitches = com.balance_pitch(robot, poses, robot.nominal_beta)
    for joints, q_base in zip(poses, pitches):
        tree = published_tree(frames, q_base, joints)
        mass = sum(m for _, m, _ in inertials)
        c = sum(m * (tree[n][1] + tree[n][0] @ c) for n, m, c in inertials) / mass
        axle = tree[BASE_LINK][1]
        assert abs(c[0] - axle[0]) < 1e-9
        assert c[2] > axle[2]
        frame0 = com.com_frame0(robot, q_base, joints[None], robot.nominal_beta)[0]
        np.testing.assert_allclose(c - axle, frame0, atol=1e-9)


def test_sitting_is_tilted_back_and_pitch_round_trips():
    """(c) On the caster base_link pitches backwards (REP-103: negative, its z leans to -x)."""
    frames = RobotFrames()
    base, pitch = frames.base_link_in_footprint(pitch_quaternion(SIT))
    assert pitch == pytest.approx(SIT, abs=1e-12) and pitch < 0
    assert base.rotation[0, 2] < 0 and base.translation[2] == pytest.approx(robot_radius())
    for q in np.linspace(-3.1, 3.1, 25):
        assert pitch_from_quaternion(*pitch_quaternion(q)) == pytest.approx(q)


def robot_radius():
    return load_krang().wheel_radius


@pytest.mark.parametrize('yaw', [0.7, -2.5, math.pi])
def test_imu_yaw_is_ignored(yaw):
    """REP-145 leaves yaw arbitrary: the pitch and base_link's attitude do not depend on it."""
    frames = RobotFrames()
    r = rot_z(yaw) @ matrix_from_quaternion(*pitch_quaternion(SIT))
    x, y, z, w = pin.Quaternion(r).coeffs()
    assert pitch_from_quaternion(x, y, z, w) == pytest.approx(SIT)
    base, pitch = frames.base_link_in_footprint((x, y, z, w))
    reference, _ = frames.base_link_in_footprint(pitch_quaternion(SIT))
    assert pitch == pytest.approx(SIT)
    np.testing.assert_allclose(base.rotation, reference.rotation, atol=1e-12)


def test_wheel_odometry():
    frames = RobotFrames()
    r, track = frames.radius, frames.track
    odom = frames.odometry
    assert (r, track) == (load_krang().wheel_radius, pytest.approx(load_krang().track_width))
    odom.update(0.0, 0.0, -0.8)
    x, _, yaw = odom.update(0.5, 0.5, -0.8)  # both wheels roll forward
    assert x == pytest.approx(0.5 * r) and yaw == 0.0
    x2, _, _ = odom.update(0.5 - 0.3, 0.5 - 0.3, -0.5)  # body pitches, wheels still on the floor
    assert x2 == pytest.approx(x)
    _, _, yaw = odom.update(0.2 - 0.1, 0.2 + 0.1, -0.5)  # right wheel ahead: a left turn (+yaw)
    assert yaw == pytest.approx(2 * 0.1 * r / track)


def test_joint_transform_follows_the_joint():
    frames = RobotFrames()
    frames.set_joints({'JWaist': 0.0})
    before = {t.child: t for t in frames.joint_transforms({'JWaist'})}['Spine']
    frames.set_joints({'JWaist': 1.0})
    after = {t.child: t for t in frames.joint_transforms({'JWaist'})}['Spine']
    np.testing.assert_allclose(after.translation, before.translation)
    turn = before.rotation.T @ after.rotation
    assert math.acos((np.trace(turn) - 1) / 2) == pytest.approx(1.0)


@pytest.mark.ros
def test_state_publisher_latches_the_urdf():
    """A late subscriber gets /robot_description (transient local); without tf2_msgs the node
    still comes up (and says in its log that /tf is not published)."""
    rclpy.init()
    try:
        node = StatePublisherNode()
        listener = rclpy.create_node('listener')
        got = []
        listener.create_subscription(
            String, ROBOT_DESCRIPTION, lambda m: got.append(m.data), LATCHED
        )
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.add_node(listener)
        deadline = time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert got and got[0] == KRANG_URDF.read_text()
        executor.shutdown()
        node.destroy_node()
        listener.destroy_node()
    finally:
        rclpy.try_shutdown()


@pytest.mark.ros
def test_state_publisher_poses_the_robot_and_its_com_at_its_frequency():
    """/joint_states at 100 Hz of stamps: /tf at publish_frequency (10 Hz), with every moving
    joint and the base; /tf_static with the fixed ones; the CoM markers in base_footprint at the
    CoM of the latest /com_estimator/beta."""
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState
    from tf2_msgs.msg import TFMessage
    from visualization_msgs.msg import MarkerArray

    from krang_com_interfaces.msg import MassModel
    from krang_core import names
    from krang_ros import messages, topics
    from krang_ros.robot_frames import com_now
    from krang_ros.state_publisher import COM_MARKERS, TF, TF_STATIC

    robot = load_krang()
    joints = np.random.default_rng(3).uniform(robot.lower, robot.upper)
    q_base = -0.05
    beta = robot.nominal_beta.copy()
    beta[4 * robot.body_names.index('Base') + 2] += 5.0  # the Base's CoM moved along its y
    rclpy.init()
    try:
        node = StatePublisherNode(parameter_overrides=[Parameter('publish_frequency', value=10.0)])
        peer = rclpy.create_node('peer')
        got = {TF: [], TF_STATIC: [], COM_MARKERS: []}
        subscriptions = [(TF, TFMessage, 100), (TF_STATIC, TFMessage, LATCHED)]
        for topic, cls, qos in subscriptions + [(COM_MARKERS, MarkerArray, 10)]:
            peer.create_subscription(cls, topic, got[topic].append, qos)
        pub_joints = peer.create_publisher(
            JointState, names.JOINT_STATES, topics.QOS[names.JOINT_STATES]
        )
        pub_imu = peer.create_publisher(Imu, names.IMU, topics.QOS[names.IMU])
        pub_beta = peer.create_publisher(MassModel, names.BETA, topics.QOS[names.BETA])
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.add_node(peer)

        def spin(seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)

        pub_beta.publish(messages.mass_model(Time(), robot.body_names, beta))
        imu = Imu()
        imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w = (
            pitch_quaternion(q_base)
        )
        spin(1.0)  # discovery
        pub_imu.publish(imu)
        spin(0.2)
        for k in range(50):
            msg = messages.joint_state(
                Time(sec=0, nanosec=10_000_000 * k),
                list(robot.pose_joints) + ['JLWheel', 'JRWheel'],
                list(joints) + [0.01 * k, 0.01 * k],
            )
            pub_joints.publish(msg)
            spin(0.01)
        spin(0.5)
        executor.shutdown()
        node.destroy_node()
        peer.destroy_node()
    finally:
        rclpy.try_shutdown()
    assert len(got[TF]) == 5  # stamps 0, 0.1, ..., 0.4 s
    frames = RobotFrames()
    children = {t.child_frame_id for t in got[TF][-1].transforms}
    assert {t.child for t in frames.joint_transforms()} | {BASE_FOOTPRINT, BASE_LINK} == children
    assert {t.child_frame_id for t in got[TF_STATIC][0].transforms} == {
        t.child for t in frames.static_transforms()
    }
    markers = got[COM_MARKERS][-1].markers
    assert {m.header.frame_id for m in markers} == {BASE_FOOTPRINT}
    frames.set_joints(dict(zip(robot.pose_joints, joints)))
    _, estimated, nominal = com_now(robot, frames, pitch_quaternion(q_base), joints, beta)
    spheres = [m for m in markers if m.type == m.SPHERE]
    assert spheres[0].pose.position.x == pytest.approx(estimated[0], abs=1e-9)
    assert spheres[1].pose.position.x == pytest.approx(nominal[0], abs=1e-9)
    assert abs(estimated[0] - nominal[0]) > 1e-3  # the beta received moved it
