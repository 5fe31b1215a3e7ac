"""The bag writer produces files that independent readers (rosbags, mcap_ros2, mcap) accept, with
the values, counts, QoS metadata and type hashes we put in; our reader agrees with them.

Expected values come from the test's own source data, never from the writer's bookkeeping.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PointStamped
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.interfaces import QosDurability, QosReliability
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from krang_bag import reader as bag_reader
from krang_bag import schemas
from krang_bag.writer import BagWriter, OfferedQos
from krang_cli import bag as bag_cli

T0 = 1_700_000_000_000_000_000
JOINTS = ['waist', 'torso', 'left_1']
BETA_LABELS = [f'b{i}' for i in range(8)]

TYPES = {
    '/joint_states': 'sensor_msgs/msg/JointState',
    '/imu/data': 'sensor_msgs/msg/Imu',
    '/wheel_effort_cmd': 'std_msgs/msg/Float64MultiArray',
    '/com_estimator/beta': 'std_msgs/msg/Float64MultiArray',
    '/com_estimator/com': 'geometry_msgs/msg/PointStamped',
    '/diagnostics': 'diagnostic_msgs/msg/DiagnosticArray',
}
QOS = {
    '/imu/data': [OfferedQos.sensor_data()],
    '/com_estimator/beta': [OfferedQos.latched()],
}
COUNTS = {
    '/joint_states': 60,
    '/imu/data': 45,
    '/wheel_effort_cmd': 30,
    '/com_estimator/beta': 3,
    '/com_estimator/com': 10,
    '/diagnostics': 5,
}


def joint_state(i):
    msg = JointState(name=JOINTS)
    msg.header.stamp.sec, msg.header.frame_id = i, 'base'
    msg.position = [np.sin(0.1 * i + k) for k in range(3)]
    msg.velocity = [np.cos(0.1 * i + k) for k in range(3)]
    msg.effort = [0.5 * k for k in range(3)]
    return msg


def imu(i):
    msg = Imu()
    msg.header.frame_id = 'imu'
    msg.angular_velocity.y = 0.01 * i
    msg.linear_acceleration.z = 9.81
    msg.orientation_covariance = np.diag([1e-3, 2e-3, 3e-3 + i]).ravel()  # numpy fields
    msg.angular_velocity_covariance = np.full(9, 0.5)
    return msg


def float_array(values, labels=None):
    msg = Float64MultiArray(data=list(values))
    if labels:
        msg.layout.dim = [
            MultiArrayDimension(label=','.join(labels), size=len(values), stride=len(values))
        ]
    return msg


def point(i):
    msg = PointStamped()
    msg.header.frame_id = 'base'
    msg.point.x, msg.point.z = 0.001 * i, 0.5
    return msg


def diagnostics(i):
    status = DiagnosticStatus(
        level=DiagnosticStatus.WARN,
        name='can_bridge',
        message=f'tick {i}',
        hardware_id='can0',
        values=[KeyValue(key='frames', value=str(100 * i))],
    )
    return DiagnosticArray(status=[status])


def source_messages():
    """(topic, log_time_ns, message) in time order, interleaving all topics."""
    makers = {
        '/joint_states': joint_state,
        '/imu/data': imu,
        '/com_estimator/com': point,
        '/diagnostics': diagnostics,
        '/wheel_effort_cmd': lambda i: float_array([0.1 * i, -0.1 * i]),
        '/com_estimator/beta': lambda i: float_array(np.arange(8) + 10.0 * i, BETA_LABELS),
    }
    slots = sorted((k / COUNTS[topic], topic, k) for topic in COUNTS for k in range(COUNTS[topic]))
    return [
        (topic, T0 + 1_000_000 * n, k, makers[topic](k)) for n, (_, topic, k) in enumerate(slots)
    ]


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('bag') / 'session.mcap'
    with BagWriter(path, chunk_size=4096) as writer:  # small chunks: many of them
        for topic, type_name in TYPES.items():
            writer.add_topic(topic, type_name, offered_qos=QOS.get(topic))
        for topic, log_time, _, msg in source_messages():
            writer.write(topic, serialize_message(msg), log_time)
    return path


def expected(topic):
    return [(log_time, k, msg) for t, log_time, k, msg in source_messages() if t == topic]


def check_values(topic, got):
    """got: [(log_time, msg)] of one topic from any reader; compare with the source messages."""
    want = expected(topic)
    assert [t for t, _ in got] == [t for t, _, _ in want]
    for (_, msg), (_, k, ref) in zip(got, want):
        if topic in ('/joint_states',):
            assert list(msg.name) == JOINTS and msg.header.frame_id == 'base'
            np.testing.assert_allclose(msg.position, ref.position)
            np.testing.assert_allclose(msg.velocity, ref.velocity)
        elif topic == '/imu/data':
            np.testing.assert_allclose(msg.orientation_covariance, ref.orientation_covariance)
            np.testing.assert_allclose(msg.angular_velocity_covariance, np.full(9, 0.5))
            assert msg.angular_velocity.y == pytest.approx(0.01 * k)
        elif topic in ('/wheel_effort_cmd', '/com_estimator/beta'):
            np.testing.assert_allclose(msg.data, ref.data)
        elif topic == '/com_estimator/com':
            assert (msg.point.x, msg.point.z) == pytest.approx((0.001 * k, 0.5))
        elif topic == '/diagnostics':
            (status,) = msg.status
            assert (status.name, status.message, status.values[0].value) == (
                'can_bridge',
                f'tick {k}',
                str(100 * k),
            )
            assert status.level in (DiagnosticStatus.WARN, DiagnosticStatus.WARN[0])


def test_rosbags_reads_bare_mcap_with_same_counts_values_and_qos(bag):
    got = {topic: [] for topic in TYPES}
    with AnyReader([Path(bag)]) as reader:
        connections = {c.topic: c for c in reader.connections}
        assert {t: c.msgtype for t, c in connections.items()} == TYPES
        for connection, timestamp, raw in reader.messages():
            got[connection.topic].append((timestamp, reader.deserialize(raw, connection.msgtype)))
        (beta_qos,) = connections['/com_estimator/beta'].ext.offered_qos_profiles
        (imu_qos,) = connections['/imu/data'].ext.offered_qos_profiles
        (joint_qos,) = connections['/joint_states'].ext.offered_qos_profiles
    assert {t: len(v) for t, v in got.items()} == COUNTS
    for topic, messages in got.items():
        check_values(topic, messages)
    assert beta_qos.durability == QosDurability.TRANSIENT_LOCAL and beta_qos.depth == 1
    assert beta_qos.reliability == QosReliability.RELIABLE
    assert (
        imu_qos.reliability == QosReliability.BEST_EFFORT
        and imu_qos.durability == QosDurability.VOLATILE
    )
    assert (
        joint_qos.reliability == QosReliability.RELIABLE
        and joint_qos.durability == QosDurability.VOLATILE
    )


def test_mcap_ros2_decodes_every_message_from_the_embedded_schemas(bag):
    got = {topic: [] for topic in TYPES}
    with open(bag, 'rb') as stream:
        for _, channel, message, decoded in make_reader(
            stream, decoder_factories=[DecoderFactory()]
        ).iter_decoded_messages():
            got[channel.topic].append((message.log_time, decoded))
    assert {t: len(v) for t, v in got.items()} == COUNTS
    for topic, messages in got.items():
        check_values(topic, messages)


def test_file_follows_the_rosbag2_mcap_contract(bag):
    with open(bag, 'rb') as stream:
        reader = make_reader(stream)
        header, summary = reader.get_header(), reader.get_summary()
    assert header.profile == 'ros2'
    stats = summary.statistics
    assert stats.message_count == sum(COUNTS.values())
    assert stats.message_start_time == T0
    assert stats.message_end_time == T0 + 1_000_000 * (sum(COUNTS.values()) - 1)
    assert stats.chunk_count == len(summary.chunk_indexes) > 3
    assert {i.compression for i in summary.chunk_indexes} == {'zstd'}
    by_topic = {c.topic: c for c in summary.channels.values()}
    assert {t: stats.channel_message_counts[c.id] for t, c in by_topic.items()} == COUNTS
    for topic, channel in by_topic.items():
        schema = summary.schemas[channel.schema_id]
        assert (schema.name, schema.encoding, channel.message_encoding) == (
            TYPES[topic],
            'ros2msg',
            'cdr',
        )
        profiles = yaml.safe_load(channel.metadata['offered_qos_profiles'])
        assert set(profiles[0]) == {
            'history',
            'depth',
            'reliability',
            'durability',
            'deadline',
            'lifespan',
            'liveliness',
            'liveliness_lease_duration',
            'avoid_ros_namespace_conventions',
        }
        assert profiles[0]['deadline'] == {'sec': 9223372036, 'nsec': 854775807}
        assert profiles[0]['history'] == 'keep_last' and profiles[0]['liveliness'] == 'automatic'
        # The type hash must be the one rosbags computes from the schema text we embedded.
        typestore = get_typestore(Stores.EMPTY)
        typestore.register(get_types_from_msg(schema.data.decode(), schema.name))
        assert channel.metadata['topic_type_hash'] == typestore.hash_rihs01(schema.name)
    assert (
        yaml.safe_load(by_topic['/com_estimator/beta'].metadata['offered_qos_profiles'])[0][
            'durability'
        ]
        == 'transient_local'
    )


def test_schema_text_and_hash_match_rosidl():
    text = schemas.message_definition('sensor_msgs/Imu')
    sections = text.split('\n' + '=' * 80 + '\n')
    assert (
        sections[0]
        .strip()
        .endswith('float64[9] linear_acceleration_covariance # Row major x, y z')
    )
    assert [s.splitlines()[0] for s in sections[1:]] == [
        'MSG: geometry_msgs/Quaternion',
        'MSG: geometry_msgs/Vector3',
        'MSG: std_msgs/Header',
        'MSG: builtin_interfaces/Time',
    ]
    # rclpy reports this hash for Imu publishers (see notes); rosidl's JSON is the source.
    assert (
        schemas.type_hash('sensor_msgs/msg/Imu')
        == 'RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b'
    )
    assert schemas.type_name_of(Imu()) == 'sensor_msgs/msg/Imu'
    with pytest.raises(schemas.SchemaNotFoundError):
        schemas.message_definition('sensor_msgs/msg/NoSuchType')
    with pytest.raises(ValueError):
        schemas.normalize_type_name('not a type')


def test_our_reader_matches_the_source(bag):
    got = {topic: [] for topic in TYPES}
    for topic, log_time, msg in bag_reader.iter_messages(bag):
        got[topic].append((log_time, msg))
    assert {t: len(v) for t, v in got.items()} == COUNTS
    for topic, messages in got.items():
        check_values(topic, messages)
        assert type(messages[0][1]).__name__ == TYPES[topic].rsplit('/', 1)[1]
    assert bag_reader.message_counts(bag) == COUNTS
    only = list(bag_reader.iter_messages(bag, topics=['/diagnostics']))
    assert [t for t, _, _ in only] == ['/diagnostics'] * COUNTS['/diagnostics']


def test_array_helpers(bag):
    series = bag_reader.read_joint_states(bag, '/joint_states')
    want = expected('/joint_states')
    assert series.names == JOINTS
    np.testing.assert_allclose(series.t, [t / 1e9 for t, _, _ in want])
    np.testing.assert_allclose(series.positions, [m.position for _, _, m in want])
    np.testing.assert_allclose(series.velocities, [m.velocity for _, _, m in want])

    t, rows = bag_reader.read_float_arrays(bag, '/com_estimator/beta')
    assert rows.shape == (3, 8)
    np.testing.assert_allclose(rows, [np.arange(8) + 10.0 * k for k in range(3)])
    np.testing.assert_allclose(t, [lt / 1e9 for lt, _, _ in expected('/com_estimator/beta')])
    _, effort = bag_reader.read_float_arrays(bag, '/wheel_effort_cmd')
    np.testing.assert_allclose(effort[:, 0], 0.1 * np.arange(30))

    with pytest.raises(bag_reader.BagError, match='not in'):
        bag_reader.read_float_arrays(bag, '/nope')
    with pytest.raises(bag_reader.BagError, match='expected'):
        bag_reader.read_joint_states(bag, '/imu/data')


def test_joint_states_with_changing_names_are_aligned(tmp_path):
    path = tmp_path / 'js.mcap'
    with BagWriter(path) as writer:
        writer.write_message(
            '/joint_states', JointState(name=['a', 'b'], position=[1.0, 2.0], velocity=[]), T0
        )
        writer.write_message(
            '/joint_states',
            JointState(name=['b', 'c'], position=[3.0, 4.0], velocity=[0.3, 0.4]),
            T0 + 1,
        )
    series = bag_reader.read_joint_states(path)
    assert series.names == ['a', 'b', 'c']
    np.testing.assert_array_equal(series.positions, [[1, 2, np.nan], [np.nan, 3, 4]])
    np.testing.assert_array_equal(series.velocities, [[np.nan] * 3, [np.nan, 0.3, 0.4]])


def test_clear_errors_for_missing_and_broken_files(tmp_path, bag):
    with pytest.raises(bag_reader.BagNotFoundError):
        bag_reader.message_counts(tmp_path / 'missing.mcap')
    with pytest.raises(FileNotFoundError):  # also a FileNotFoundError for generic callers
        list(bag_reader.iter_messages(tmp_path / 'missing.mcap'))
    junk = tmp_path / 'junk.mcap'
    junk.write_bytes(b'this is not an mcap file at all' * 10)
    with pytest.raises(bag_reader.BagCorruptError, match='not an MCAP'):
        bag_reader.message_counts(junk)
    torn = tmp_path / 'torn.mcap'
    torn.write_bytes(Path(bag).read_bytes()[:5000])
    with pytest.raises(bag_reader.BagCorruptError, match='recover'):
        list(bag_reader.iter_messages(torn))


def test_writer_refuses_to_clobber_and_to_write_unknown_topics(tmp_path, bag):
    with pytest.raises(FileExistsError):
        BagWriter(bag)
    with BagWriter(tmp_path / 'x.mcap') as writer:
        with pytest.raises(KeyError):
            writer.write('/never_added', b'', T0)
        writer.add_topic('/a', 'std_msgs/Float64MultiArray')
        with pytest.raises(ValueError):
            writer.add_topic('/a', 'sensor_msgs/msg/Imu')


def test_cli_info(bag, capsys):
    assert bag_cli.main(['info', str(bag)]) == 0
    out = capsys.readouterr().out
    assert (
        'Messages:    153' in out
        and 'best_effort/volatile' in out
        and 'reliable/transient_local' in out
    )
    for topic in TYPES:
        line = next(line for line in out.splitlines() if line.split()[:1] == [topic])
        assert line.split()[1:3] == [TYPES[topic], str(COUNTS[topic])]
    assert bag_cli.main(['info', str(bag), '--json']) == 0
    info = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert {t: v['count'] for t, v in info['topics'].items()} == COUNTS
    assert info['duration_s'] == pytest.approx((sum(COUNTS.values()) - 1) * 1e-3)
    assert bag_cli.main(['info', str(bag) + '.missing']) == 1
    assert 'not found' in capsys.readouterr().err


def test_cli_help_explains(capsys):
    for argv in (['--help'], ['info', '--help'], ['recover', '--help']):
        with pytest.raises(SystemExit) as exit_:
            bag_cli.main(argv)
        assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert 'never finished' in text and 'chunk' in text and 'topics, message types' in text


def test_bag_without_statistics_is_counted_by_scanning(tmp_path):
    """Other writers may omit the statistics record; counts then come from reading the file."""
    from mcap.writer import Writer

    path = tmp_path / 'nostats.mcap'
    with open(path, 'wb') as stream:
        writer = Writer(stream, use_statistics=False)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema(
            'std_msgs/msg/Float64MultiArray',
            'ros2msg',
            schemas.message_definition('std_msgs/msg/Float64MultiArray').encode(),
        )
        channel = writer.register_channel('/wheel_effort_cmd', 'cdr', schema)
        for i in range(7):
            writer.add_message(channel, T0 + i, serialize_message(float_array([i, -i])), T0 + i)
        writer.finish()
    info = bag_reader.bag_info(path)
    assert (info.message_count, info.start_ns, info.end_ns) == (7, T0, T0 + 6)
    assert bag_reader.message_counts(path) == {'/wheel_effort_cmd': 7}
    _, rows = bag_reader.read_float_arrays(path, '/wheel_effort_cmd')
    np.testing.assert_allclose(rows[:, 1], -np.arange(7))


DATA = Path(__file__).resolve().parent / 'data'


def plain(value):
    """A decoded message as plain values (its fields by name, lists for arrays)."""
    slots = getattr(value, '__slots__', None)
    if slots is not None and not isinstance(value, (str, bytes)):
        return {name: plain(getattr(value, name)) for name in slots}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value.tolist() if hasattr(value, 'tolist') else value


def test_a_bag_recorded_as_the_nodes_publish_reads_the_same():
    """session_bag_v1.mcap: the messages our nodes publish, serialized by rclpy as DDS delivers
    them and written by the recorder's path; the JSON beside it holds their values as rclpy
    deserializes them (NaN included)."""
    expected = json.loads((DATA / 'session_bag_v1.json').read_text())
    got = {}
    for topic, log_time, msg in bag_reader.iter_messages(DATA / 'session_bag_v1.mcap'):
        got.setdefault(topic, []).append([log_time, plain(msg)])
    assert json.dumps(got, sort_keys=True) == json.dumps(expected, sort_keys=True)
    series = bag_reader.read_joint_states(DATA / 'session_bag_v1.mcap')
    np.testing.assert_array_equal(
        series.positions[:, 0], [m['position'][0] for _, m in expected['/joint_states']]
    )


def test_reading_a_bag_imports_no_ros_package():
    """The offline readers (krang_bag.reader, relearn, the discrepancy loaders) in a process where
    rclpy and every message package fail to import."""
    script = (
        'import importlib.abc, sys\n'
        'class NoRos(importlib.abc.MetaPathFinder):\n'
        '    def find_spec(self, name, path=None, target=None):\n'
        "        top = name.split('.')[0]\n"
        "        if top in ('rclpy', 'rosidl_parser', 'builtin_interfaces', 'krang_ros') or "
        "top.endswith(('_msgs', '_srvs', '_interfaces')):\n"
        "            raise ImportError('no ROS here: ' + name)\n"
        'sys.meta_path.insert(0, NoRos())\n'
        'from krang_bag import reader, relearn, session_report\n'
        'from krang_discrepancy import loaders\n'
        f'print(sum(reader.message_counts({str(DATA / "session_bag_v1.mcap")!r}).values()),\n'
        f'      len(list(reader.iter_messages({str(DATA / "session_bag_v1.mcap")!r}))))\n'
    )
    count = sum(map(len, json.loads((DATA / 'session_bag_v1.json').read_text()).values()))
    result = subprocess.run(
        [sys.executable, '-c', script], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == [str(count)] * 2
