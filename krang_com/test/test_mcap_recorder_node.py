"""mcap_recorder: its plain decisions (no ROS), then the real node as a subprocess over DDS.

The ROS tests publish a known number of messages and check the bag with rosbags and mcap_ros2 —
never with the recorder's own counters.
"""

import os
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag2.metadata import parse_qos
from rosbags.interfaces import QosDurability, QosReliability

from krang_bag.node import offered_qos_from_profile
from krang_bag.recording import (
    RequestQos,
    choose_request_qos,
    plan_new_topics,
    resolve_output_path,
    topic_selected,
)
from krang_bag.writer import DURATION_INFINITE_NS, OfferedQos, offered_qos_yaml

REPO = Path(__file__).resolve().parents[1]
RELIABLE, BEST_EFFORT = OfferedQos(), OfferedQos.sensor_data()
LATCHED = OfferedQos.latched()


# ------------------------------------------------------------------ plain functions, no ROS


def test_qos_request_is_the_strongest_that_matches_every_offer():
    assert choose_request_qos([RELIABLE, RELIABLE]) == RequestQos(True, False, 100)
    assert choose_request_qos([RELIABLE, BEST_EFFORT]) == RequestQos(False, False, 100)
    assert choose_request_qos([LATCHED]) == RequestQos(True, True, 100)
    # volatile joins
    assert choose_request_qos([LATCHED, RELIABLE]) == RequestQos(True, False, 100)
    assert choose_request_qos([OfferedQos(depth=500)], min_depth=10).depth == 500
    assert choose_request_qos([OfferedQos(history='unknown', depth=0)], min_depth=10).depth == 10
    # rosbag2 default
    assert choose_request_qos([]) == RequestQos(True, False, 100)


def test_topic_selection():
    assert topic_selected('/imu/data')
    assert not topic_selected('/imu/data', exclude=['/imu/*'])
    assert topic_selected('/imu/data', include=['/imu/*', '/joint_states'])
    assert not topic_selected('/diagnostics', include=['/imu/*'])
    assert not topic_selected('/_hidden/x') and topic_selected('/_hidden/x', include_hidden=True)
    # named explicitly
    assert topic_selected('/_hidden/x', include=['/_hidden/x'])
    add, skipped = plan_new_topics(
        [
            ('/b', ['std_msgs/msg/String']),
            ('/a', ['sensor_msgs/msg/Imu']),
            ('/done', ['std_msgs/msg/Bool']),
            ('/mixed', ['std_msgs/msg/String', 'std_msgs/msg/Bool']),
            ('/rosout', ['rcl_interfaces/msg/Log']),
        ],
        recorded={'/done'},
        exclude=['/rosout'],
    )
    assert add == [('/a', 'sensor_msgs/msg/Imu'), ('/b', 'std_msgs/msg/String')]
    assert list(skipped) == ['/mixed']


def test_output_path(tmp_path):
    now = datetime(2025, 3, 4, 5, 6, 7)
    assert resolve_output_path('', now) == Path('krang_2025_03_04-05_06_07.mcap')
    assert resolve_output_path(str(tmp_path), now) == tmp_path / 'krang_2025_03_04-05_06_07.mcap'
    assert (
        resolve_output_path(str(tmp_path / 'new') + '/', now)
        == tmp_path / 'new' / 'krang_2025_03_04-05_06_07.mcap'
    )
    assert resolve_output_path(str(tmp_path / 'run.mcap'), now) == tmp_path / 'run.mcap'


def test_offered_qos_from_rclpy_profiles_reads_back_in_rosbags():
    from rclpy.qos import QoSDurabilityPolicy, QoSProfile, qos_profile_sensor_data

    latched = offered_qos_from_profile(
        QoSProfile(depth=1, durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)
    )
    sensor = offered_qos_from_profile(qos_profile_sensor_data)
    assert (latched.reliability, latched.durability, latched.depth) == (
        'reliable',
        'transient_local',
        1,
    )
    assert (sensor.reliability, sensor.durability, sensor.history) == (
        'best_effort',
        'volatile',
        'keep_last',
    )
    parsed = parse_qos(offered_qos_yaml([latched, sensor, OfferedQos(history='unknown', depth=0)]))
    assert [q.durability for q in parsed] == [
        QosDurability.TRANSIENT_LOCAL,
        QosDurability.VOLATILE,
        QosDurability.VOLATILE,
    ]
    assert [q.reliability for q in parsed][:2] == [
        QosReliability.RELIABLE,
        QosReliability.BEST_EFFORT,
    ]
    assert yaml.safe_load(offered_qos_yaml([OfferedQos()]))[0]['lifespan'] == {
        'sec': DURATION_INFINITE_NS // 10**9,
        'nsec': DURATION_INFINITE_NS % 10**9,
    }


# ------------------------------------------------------------------ the node over DDS

N_PER_TOPIC = 40


def start_recorder(*ros_params):
    args = [sys.executable, '-m', 'krang_bag.node', '--ros-args', '-p', 'poll_period_s:=0.2']
    for param in ros_params:
        args += ['-p', param]
    # The environment (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE from conftest) is inherited.
    return subprocess.Popen(
        args,
        cwd=REPO,
        env=os.environ.copy(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.fixture
def ros_domain(monkeypatch, request):
    """A domain of its own per test (101..232, above conftest's 1..100 range), inherited by the
    recorder."""
    domain = 101 + (os.getpid() * 31 + sum(map(ord, request.node.name))) % 132
    monkeypatch.setenv('ROS_DOMAIN_ID', str(domain))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    return domain


@pytest.fixture
def publisher_node(ros_domain):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('bag_test_publisher', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=context)


def make_publishers(node):
    from rclpy.qos import QoSDurabilityPolicy, QoSProfile, qos_profile_sensor_data
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64MultiArray

    return {
        '/joint_states': node.create_publisher(JointState, '/joint_states', 10),
        '/imu/data': node.create_publisher(Imu, '/imu/data', qos_profile_sensor_data),
        '/wheel_effort_cmd': node.create_publisher(Float64MultiArray, '/wheel_effort_cmd', 50),
        '/com_estimator/beta': node.create_publisher(
            Float64MultiArray,
            '/com_estimator/beta',
            QoSProfile(depth=1, durability=QoSDurabilityPolicy.TRANSIENT_LOCAL),
        ),
    }


def message_for(topic, i):
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64MultiArray

    if topic == '/joint_states':
        return JointState(name=['waist'], position=[float(i)])
    if topic == '/imu/data':
        msg = Imu()
        msg.angular_velocity.y = float(i)
        return msg
    return Float64MultiArray(data=[float(i), 0.5])


def spin_until(executor, condition, timeout, what):
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f'timed out waiting for {what}'
        executor.spin_once(timeout_sec=0.05)


def spin_for(executor, seconds):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.02)


def publish_all(node, executor, publishers, proc, beta_published_before):
    """Wait until the recorder matched every publisher, then publish; returns counts per topic."""

    def recorder_matched():
        assert proc.poll() is None, f'recorder exited early: {proc.communicate()[1]}'
        return all(
            node.count_subscribers(t) >= 1 and p.get_subscription_count() >= 1
            for t, p in publishers.items()
        )

    spin_until(executor, recorder_matched, 20, 'the recorder to subscribe')
    spin_for(executor, 0.3)
    published = {topic: 0 for topic in publishers}
    published['/com_estimator/beta'] = beta_published_before
    for i in range(N_PER_TOPIC):
        for topic, publisher in publishers.items():
            if topic == '/com_estimator/beta' and i % 10:
                continue  # latched topic: a few messages only
            publisher.publish(message_for(topic, i))
            published[topic] += 1
        spin_for(executor, 0.004)
    spin_for(executor, 1.0)  # let the recorder take everything before it is stopped
    return published


def bag_counts_rosbags(path):
    counts, values = {}, {}
    with AnyReader([Path(path)]) as reader:
        for connection, _, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
            if connection.topic == '/joint_states':
                values.setdefault('/joint_states', []).append(msg.position[0])
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    return counts, values, qos


def bag_counts_mcap_ros2(path):
    counts = {}
    with open(path, 'rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        for _, channel, _, _ in reader.iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
        channels = {c.topic: c for c in reader.get_summary().channels.values()}
    return counts, channels


@pytest.mark.ros
@pytest.mark.timeout(60)
@pytest.mark.parametrize('stop_signal', [signal.SIGTERM, signal.SIGINT], ids=['SIGTERM', 'SIGINT'])
def test_recorder_bag_holds_every_published_message(publisher_node, tmp_path, stop_signal):
    node, executor = publisher_node
    publishers = make_publishers(node)
    # Latched before the recorder exists: it must still arrive (transient_local request).
    publishers['/com_estimator/beta'].publish(message_for('/com_estimator/beta', -1))
    bag = tmp_path / 'rec' / 'session.mcap'
    extra = ["exclude:=['/rosout', '/parameter_events']"] if stop_signal == signal.SIGINT else []
    proc = start_recorder(f'output:={bag}', *extra)
    try:
        published = publish_all(node, executor, publishers, proc, beta_published_before=1)
        proc.send_signal(stop_signal)
        _, stderr = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    assert 'recording /imu/data' in stderr and 'finished' in stderr

    counts, values, qos = bag_counts_rosbags(bag)
    ours = {t: c for t, c in counts.items() if t in publishers}
    assert ours == published
    assert values['/joint_states'] == [float(i) for i in range(N_PER_TOPIC)]
    mcap_counts, channels = bag_counts_mcap_ros2(bag)
    assert mcap_counts == counts
    if stop_signal == signal.SIGINT:
        assert set(counts) == set(publishers)  # excluded topics stayed out
    else:
        assert {'/rosout'} <= set(counts)  # everything discovered is recorded

    assert qos['/imu/data'][0].reliability == QosReliability.BEST_EFFORT
    assert qos['/com_estimator/beta'][0].durability == QosDurability.TRANSIENT_LOCAL
    assert qos['/joint_states'][0].reliability == QosReliability.RELIABLE
    from krang_bag.schemas import type_hash

    assert channels['/imu/data'].metadata['topic_type_hash'] == type_hash('sensor_msgs/msg/Imu')


@pytest.mark.ros
@pytest.mark.timeout(60)
def test_recorder_killed_with_sigkill_is_recoverable(publisher_node, tmp_path):
    from krang_bag.recover import recover

    node, executor = publisher_node
    publishers = make_publishers(node)
    bag = tmp_path / 'killed.mcap'
    proc = start_recorder(
        f'output:={bag}',
        'chunk_size:=1024',
        "topics:=['/joint_states', '/imu/data', '/wheel_effort_cmd', '/com_estimator/beta']",
    )
    try:
        published = publish_all(node, executor, publishers, proc, beta_published_before=0)
        spin_for(executor, 0.5)  # one more poll tick: the recorder flushes completed chunks
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    with pytest.raises(Exception):
        with AnyReader([bag]) as reader:
            list(reader.messages())
    report = recover(bag, tmp_path / 'rescued.mcap')
    counts, values, _ = bag_counts_rosbags(report.output)
    assert report.truncated and report.messages == sum(counts.values()) > 0
    assert set(counts) <= set(publishers)  # the `topics` include list was honoured
    assert all(counts[t] <= published[t] for t in counts)
    # a prefix
    assert values['/joint_states'] == [float(i) for i in range(len(values['/joint_states']))]


@pytest.mark.ros
def test_recorder_never_overwrites_a_bag(tmp_path, ros_domain):
    bag = tmp_path / 'exists.mcap'
    bag.write_bytes(b'precious')
    proc = start_recorder(f'output:={bag}')
    _, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 1 and 'refusing to overwrite' in stderr
    assert bag.read_bytes() == b'precious'
