"""A bag of the node set opens in Foxglove with the robot drawn and posed and its CoM shown: it
carries the URDF on /robot_description, the tf tree of every link on /tf and /tf_static (each frame
id one of the URDF's links or REP-105's odom and base_footprint), /imu/data in a link of the URDF,
and the CoM markers in a frame of the tree; rosbags reads all of it from the bag alone."""

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('tf2_msgs.msg')

from rosbags.highlevel import AnyReader  # noqa: E402

from krang_cli.composed import ComposedSimulation  # noqa: E402
from krang_cli.node_set import file_parameter  # noqa: E402
from krang_core import names  # noqa: E402
from krang_model.robot import KRANG_URDF  # noqa: E402
from krang_ros.robot_frames import BASE_FOOTPRINT, ODOM  # noqa: E402
from krang_ros.state_publisher import COM_MARKERS, ROBOT_DESCRIPTION, TF, TF_STATIC  # noqa: E402
from krang_sim.session_config import session_devices_file  # noqa: E402

SECONDS = 2.0  # of simulated time, the robot sitting


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """The composed node set of `krang demo`, recorded for SECONDS of simulated time."""
    out = tmp_path_factory.mktemp('foxglove')
    devices = str(session_devices_file(out, virtual=True))
    path = out / 'session.mcap'
    composed = ComposedSimulation(
        {
            'sim_krang': {'devices_file': devices, 'real_time_factor': 0.0},
            'can_bridge': {'devices_file': devices},
        },
        record=path,
    )
    try:
        start = composed.sim_time
        while composed.sim_time < start + SECONDS:
            composed.advance()
    finally:
        composed.close()
    return path


def seconds(stamp):
    return stamp.sec + 1e-9 * stamp.nanosec


def read(path):
    """{topic: [message]} and {topic: type} as rosbags reads them from the bag alone."""
    got = {}
    with AnyReader([Path(path)]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for connection, _, raw in reader.messages():
            got.setdefault(connection.topic, []).append(
                reader.deserialize(raw, connection.msgtype)
            )
    return got, types


def test_the_bag_draws_and_poses_the_robot_and_its_com(bag):
    got, types = read(bag)
    assert types[ROBOT_DESCRIPTION] == 'std_msgs/msg/String'
    assert types[TF] == types[TF_STATIC] == 'tf2_msgs/msg/TFMessage'
    assert types[COM_MARKERS] == 'visualization_msgs/msg/MarkerArray'
    urdf_text = KRANG_URDF.read_text()
    assert [m.data for m in got[ROBOT_DESCRIPTION]] == [urdf_text]
    urdf = ET.fromstring(urdf_text)
    links = {link.get('name') for link in urdf.findall('link')}
    joints = urdf.findall('joint')
    fixed = {j.find('child').get('link') for j in joints if j.get('type') == 'fixed'}
    moving = {j.find('child').get('link') for j in joints if j.get('type') != 'fixed'}
    frames = links | {ODOM, BASE_FOOTPRINT}

    (static,) = got[TF_STATIC]
    edges = {(t.header.frame_id, t.child_frame_id) for t in static.transforms}
    # base_link -> Base is the URDF's fixed joint Base -> base_link, inverted (REP-105 root)
    assert {c for _, c in edges} == (fixed - {'base_link'}) | {'Base'}
    # publish_frequency a second of the /joint_states stamps, as the set's parameters give it
    rate = file_parameter('state_publisher', 'publish_frequency', sim=True)
    stamps = [seconds(m.transforms[0].header.stamp) for m in got[TF]]
    joint_stamps = [seconds(m.header.stamp) for m in got[names.JOINT_STATES]]
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    assert 1 / rate - 1e-9 <= min(gaps) and max(gaps) < 1 / rate + 0.02  # + a sample period
    # from the first samples (its subscription matches a moment after the recorder's) to the last
    assert stamps[0] - joint_stamps[0] < 0.5 and joint_stamps[-1] - stamps[-1] < 1 / rate
    for msg in got[TF]:
        children = {t.child_frame_id for t in msg.transforms}
        assert children == moving | {BASE_FOOTPRINT, 'base_link'}
        assert {t.header.frame_id for t in msg.transforms} <= frames
    assert {p for p, _ in edges} <= frames

    imu_frames = {m.header.frame_id for m in got[names.IMU]}
    assert imu_frames == {'imu_link'} and imu_frames <= links

    assert len(got[COM_MARKERS]) == len(got[TF])
    markers = got[COM_MARKERS][-1].markers
    assert {m.header.frame_id for m in markers} == {BASE_FOOTPRINT}
    assert [m.type for m in markers] == [4, 4, 2, 2, 9]  # lines, spheres, a text
    assert markers[-1].text.startswith('CoM ')
