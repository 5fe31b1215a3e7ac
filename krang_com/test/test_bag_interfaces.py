"""Bags of the robot's own types (krang_com_interfaces) and of its frames (the state_publisher's
topics): rosbags and mcap_ros2 rebuild every type from the definitions the bag carries, with the
type hash rosidl gives it; relearn reads today's types and the older forms alike.

test/data/session_learning_v1.mcap holds the learning topics of a 3-pose `krang demo` recorded
before krang_com_interfaces existed, as the recorder wrote them: /balanced_pose as JointState
(standard errors in `effort`), /com_estimator/beta as Float64MultiArray, /adrc_controller/mode and
/can_bridge/drive_fault as String.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from std_msgs.msg import String

from krang_adrc_controller.detector import BalancedPoint
from krang_bag import schemas
from krang_bag.reader import bag_info, iter_messages
from krang_bag.relearn import balanced_poses, recorded_betas, relearn
from krang_bag.writer import BagWriter, OfferedQos
from krang_cli.main import main
from krang_cli.relearn import REPRODUCTION_TOLERANCE
from krang_core import message_values, names
from krang_model.robot import load_krang
from krang_ros import messages
from krang_ros.robot_frames import RobotFrames, com_marks, com_now
from krang_ros.state_publisher import (
    COM_MARKERS,
    ROBOT_DESCRIPTION,
    TF,
    TF_STATIC,
    ComMarkers,
    transform_stamped,
)

tf2_msgs = pytest.importorskip('tf2_msgs.msg')

DATA = Path(__file__).parent / 'data'
OLDER_BAG = DATA / 'session_learning_v1.mcap'
T0 = 1_700_000_000_000_000_000
TYPES = {
    names.BALANCED_POSE: 'krang_com_interfaces/msg/BalancedPose',
    names.BETA: 'krang_com_interfaces/msg/MassModel',
    names.MODE: 'krang_com_interfaces/msg/ControllerMode',
    names.DRIVE_FAULT: 'krang_com_interfaces/msg/DriveFault',
    names.ARM_FAULT: 'krang_com_interfaces/msg/ArmFault',
    names.STAND_ESTIMATE: 'krang_com_interfaces/msg/StandEstimate',
    ROBOT_DESCRIPTION: 'std_msgs/msg/String',
    TF: 'tf2_msgs/msg/TFMessage',
    TF_STATIC: 'tf2_msgs/msg/TFMessage',
    COM_MARKERS: 'visualization_msgs/msg/MarkerArray',
}


@pytest.fixture(scope='module')
def robot():
    return load_krang()


def source_messages(robot):
    """{topic: [message]} of every type, with values that are not their defaults."""
    rng = np.random.default_rng(7)
    n = len(robot.pose_joints)
    stamp = messages.stamp(12.5)
    poses = [
        messages.balanced_pose(
            stamp,
            robot.pose_joints,
            BalancedPoint(
                t=12.5,
                q_base=-0.01 * k,
                joints=rng.uniform(robot.lower, robot.upper),
                q_base_std=0.004,
                n_samples=200,
                window_s=2.0,
                q_base_se=3e-4,
                joints_se=np.full(n, 1e-4),
            ),
        )
        for k in range(3)
    ]
    cov = np.diag(rng.uniform(0.1, 1.0, robot.n_beta))
    models = [
        messages.mass_model(
            stamp, robot.body_names, robot.nominal_beta * (1 + 0.01 * k), cov, 'map-online', k
        )
        for k in range(3)
    ]
    frames = RobotFrames()
    joints = dict(zip(robot.pose_joints, poses[0].positions)) | {'JLWheel': 0.3, 'JRWheel': 0.2}
    frames.set_joints(joints)
    imu = (0.0, 0.05, 0.0, float(np.sqrt(1 - 0.05**2)))
    moving = frames.joint_transforms() + frames.base_transforms(imu, 0.3, 0.2)
    marks = com_marks(*com_now(robot, frames, imu, poses[0].positions, models[1].beta), 0.3)
    return {
        names.BALANCED_POSE: poses,
        names.BETA: models,
        names.MODE: [messages.controller_mode(stamp, m) for m in ('sit', 'stand_up', 'balance')],
        names.DRIVE_FAULT: [messages.drive_fault(stamp, r) for r in ('left drive rebooted', '')],
        names.ARM_FAULT: [
            messages.arm_fault(stamp, 'arm module LJ2 not answering', ['LJ2']),
            messages.arm_fault(stamp, '', []),
        ],
        names.STAND_ESTIMATE: [
            messages.stand_estimate(stamp, k, 3, -0.1044 / k, (-0.20944, 0.0)) for k in (1, 2)
        ],
        ROBOT_DESCRIPTION: [String(data=frames.urdf_text)],
        TF: [tf2_msgs.TFMessage(transforms=[transform_stamped(stamp, t) for t in moving])],
        TF_STATIC: [
            tf2_msgs.TFMessage(
                transforms=[transform_stamped(stamp, t) for t in frames.static_transforms()]
            )
        ],
        COM_MARKERS: [ComMarkers().update(stamp, marks)],
    }


@pytest.fixture(scope='module')
def bag(robot, tmp_path_factory):
    """Written as the recorder writes: the CDR bytes rclpy serializes, under the installed
    definitions."""
    path = tmp_path_factory.mktemp('bag') / 'interfaces.mcap'
    latched = {
        names.BETA,
        names.MODE,
        names.DRIVE_FAULT,
        names.ARM_FAULT,
        names.STAND_ESTIMATE,
        ROBOT_DESCRIPTION,
        TF_STATIC,
    }
    with BagWriter(path) as writer:
        for k, (topic, batch) in enumerate(source_messages(robot).items()):
            writer.add_topic(
                topic,
                TYPES[topic],
                offered_qos=[OfferedQos.latched()] if topic in latched else None,
            )
            for i, msg in enumerate(batch):
                writer.write(topic, serialize_message(msg), T0 + 10**6 * (100 * k + i))
    return path


def fields(msg, name):
    """A field of a message from rclpy, rosbags or mcap_ros2, as plain Python values."""
    value = getattr(msg, name)
    return value.tolist() if hasattr(value, 'tolist') else list(value)


def check(robot, topic, got):
    """The decoded messages of one topic (any reader) against the source."""
    want = source_messages(robot)[topic]
    assert len(got) == len(want)
    for a, b in zip(got, want):
        if topic == names.BALANCED_POSE:
            assert list(a.joint_names) == list(robot.pose_joints)
            for name in ('positions', 'position_standard_errors'):
                np.testing.assert_array_equal(fields(a, name), fields(b, name))
            assert (a.base_pitch, a.base_pitch_standard_error, a.samples) == (
                b.base_pitch,
                b.base_pitch_standard_error,
                b.samples,
            )
            assert (a.settle_window.sec, a.header.stamp.nanosec) == (2, 500_000_000)
        elif topic == names.BETA:
            assert list(a.body_names) == list(robot.body_names) and a.source == 'map-online'
            np.testing.assert_array_equal(fields(a, 'beta'), fields(b, 'beta'))
            np.testing.assert_array_equal(fields(a, 'covariance'), fields(b, 'covariance'))
            assert a.poses == b.poses
        elif topic == names.MODE:
            assert (a.mode, a.name) == (b.mode, b.name)
        elif topic == names.DRIVE_FAULT:
            assert (a.active, a.reason) == (b.active, b.reason)
        elif topic == names.ARM_FAULT:
            assert (a.active, list(a.joints), a.reason) == (b.active, list(b.joints), b.reason)
        elif topic == names.STAND_ESTIMATE:
            values = ('tries', 'tries_max', 'com_angle_error', 'stand_window_min')
            assert [getattr(a, v) for v in values] == [getattr(b, v) for v in values]
        elif topic == ROBOT_DESCRIPTION:
            assert a.data == b.data
        elif topic in (TF, TF_STATIC):
            assert [(t.header.frame_id, t.child_frame_id) for t in a.transforms] == [
                (t.header.frame_id, t.child_frame_id) for t in b.transforms
            ]
            assert [t.transform.rotation.w for t in a.transforms] == [
                t.transform.rotation.w for t in b.transforms
            ]
        elif topic == COM_MARKERS:
            assert [(m.type, m.header.frame_id, m.text) for m in a.markers] == [
                (m.type, m.header.frame_id, m.text) for m in b.markers
            ]
            assert a.markers[2].pose.position.x == b.markers[2].pose.position.x


def test_rosbags_reads_every_type_from_the_definitions_in_the_bag(robot, bag):
    got = {}
    with AnyReader([bag]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == TYPES
        for connection, _, raw in reader.messages():
            got.setdefault(connection.topic, []).append(
                reader.deserialize(raw, connection.msgtype)
            )
    for topic in TYPES:
        check(robot, topic, got[topic])


def test_mcap_ros2_and_our_reader_decode_every_type(robot, bag):
    got = {}
    with open(bag, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages():
            got.setdefault(channel.topic, []).append(decoded)
    ours = {}
    for topic, _, msg in iter_messages(bag):
        ours.setdefault(topic, []).append(msg)
    for topic in TYPES:
        check(robot, topic, got[topic])
        check(robot, topic, ours[topic])


def test_each_definition_hashes_as_rosidl_installed_it(bag):
    """The schema text is complete and exact: rosbags' hash of it is rosidl's (what rclpy
    offers on the wire), for the project's types and the frames' alike."""
    with open(bag, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        typestore = get_typestore(Stores.EMPTY)
        typestore.register(get_types_from_msg(schema.data.decode(), schema.name))
        assert typestore.hash_rihs01(schema.name) == schemas.type_hash(schema.name)
        assert channel.metadata['topic_type_hash'] == schemas.type_hash(schema.name)


def test_the_readers_take_the_values_of_todays_types(robot, bag):
    sent = source_messages(robot)
    poses = balanced_poses(bag, robot)
    assert [p[0] for p in poses] == [m.base_pitch for m in sent[names.BALANCED_POSE]]
    assert [p[2] for p in poses] == [3e-4] * 3
    np.testing.assert_array_equal(recorded_betas(bag, robot), [m.beta for m in sent[names.BETA]])
    modes = [message_values.mode_name(m) for _, _, m in iter_messages(bag, [names.MODE])]
    assert modes == ['sit', 'stand_up', 'balance']
    faults = [
        message_values.drive_fault_reason(m) for _, _, m in iter_messages(bag, [names.DRIVE_FAULT])
    ]
    assert faults == ['left drive rebooted', '']


def test_krang_relearn_replays_an_older_bag(tmp_path, capsys):
    """The online estimator's betas in the older bag are reproduced from its poses."""
    assert bag_info(OLDER_BAG).topics[names.BALANCED_POSE].type_name == (
        'sensor_msgs/msg/JointState'
    )
    out = tmp_path / 'relearned.yaml'
    assert main(['relearn', str(OLDER_BAG), '--out', str(out), '--json']) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary['poses'] == 3 and summary['online_betas'] == 4
    assert summary['max_rel_diff_to_online'] <= REPRODUCTION_TOLERANCE
    assert out.exists()


def test_an_older_bag_and_its_today_form_relearn_the_same(robot, tmp_path):
    """The older bag's poses and betas rewritten as BalancedPose and MassModel replay to the same
    betas, bit for bit."""
    today = tmp_path / 'today.mcap'
    with BagWriter(today) as writer:
        writer.add_topic(names.BALANCED_POSE, TYPES[names.BALANCED_POSE])
        writer.add_topic(names.BETA, TYPES[names.BETA], offered_qos=[OfferedQos.latched()])
        for topic, t_ns, msg in iter_messages(OLDER_BAG, [names.BALANCED_POSE, names.BETA]):
            if topic == names.BETA:
                new = messages.mass_model(messages.stamp(0.0), robot.body_names, msg.data)
            else:
                pose = message_values.balanced_pose_values(msg, robot.pose_joints)
                point = BalancedPoint(
                    t=0.0,
                    q_base=pose.q_base,
                    joints=pose.joints,
                    q_base_std=0.0,
                    n_samples=0,
                    window_s=0.0,
                    q_base_se=pose.q_base_se,
                    joints_se=pose.joints_se,
                )
                new = messages.balanced_pose(messages.stamp(0.0), robot.pose_joints, point)
            writer.write(topic, serialize_message(new), t_ns)
    older, now = relearn(OLDER_BAG, robot), relearn(today, robot)
    assert len(older.poses) == len(now.poses) == 3
    np.testing.assert_array_equal(older.betas, now.betas)
    np.testing.assert_array_equal(older.recorded, now.recorded)
