"""Recovery of bags that were never finished: torn copies of a finished bag, and a writer
killed -9.

What "should" be recovered is computed from the intact original's chunk index (messages of every
chunk that lies wholly before the cut), and payloads are compared byte for byte with the original.
"""

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from std_msgs.msg import Float64MultiArray

from krang_bag.reader import BagCorruptError, BagNotFoundError, message_counts
from krang_bag.recover import recover
from krang_bag.writer import BagWriter, OfferedQos
from krang_cli import bag as bag_cli

REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000
N = 400


def read_all(path):
    """[(topic, log_time, data)] and the summary, read by mcap's seeking reader."""
    with open(path, 'rb') as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        return [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages()], summary


def unreadable_by_standard_readers(path) -> bool:
    """True when both mcap's make_reader and rosbags refuse the file."""
    try:
        read_all(path)
        return False
    except Exception:
        pass
    try:
        with AnyReader([Path(path)]) as reader:
            list(reader.messages())
        return False
    except Exception:
        return True


def rosbags_counts(path):
    counts = {}
    with AnyReader([Path(path)]) as reader:
        for connection, _, raw in reader.messages():
            reader.deserialize(raw, connection.msgtype)
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    return counts


@pytest.fixture(scope='module')
def original(tmp_path_factory):
    path = tmp_path_factory.mktemp('orig') / 'finished.mcap'
    with BagWriter(path, chunk_size=2048) as writer:
        writer.add_topic(
            '/com_estimator/beta',
            'std_msgs/msg/Float64MultiArray',
            offered_qos=[OfferedQos.latched()],
        )
        for i in range(N):
            writer.write_message(
                '/wheel_effort_cmd' if i % 4 else '/com_estimator/beta',
                Float64MultiArray(data=[float(i), -float(i), 0.5]),
                T0 + 1000 * i,
            )
    messages, summary = read_all(path)
    assert len(messages) == N and len(summary.chunk_indexes) > 10
    return path, messages, summary


def cut_points(summary, data_end):
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    middle = chunks[len(chunks) // 2]
    return {
        'mid_chunk': middle.chunk_start_offset + middle.chunk_length // 2,
        'inside_chunk_header': middle.chunk_start_offset + 5,
        'right_after_a_chunk': middle.chunk_start_offset + middle.chunk_length,
        'one_chunk_in': chunks[0].chunk_start_offset + chunks[0].chunk_length + 3,
        'nothing_complete': chunks[0].chunk_start_offset + 10,
        'ninety_percent_of_data': int(0.9 * data_end),
    }


def expected_prefix(messages, summary, cut):
    """Messages of the chunks that end before the cut (log times increase with file order here)."""
    complete = [
        c.message_end_time
        for c in summary.chunk_indexes
        if c.chunk_start_offset + c.chunk_length <= cut
    ]
    last = max(complete, default=-1)
    return [m for m in messages if m[1] <= last]


@pytest.mark.parametrize(
    'where',
    [
        'mid_chunk',
        'inside_chunk_header',
        'right_after_a_chunk',
        'one_chunk_in',
        'nothing_complete',
        'ninety_percent_of_data',
    ],
)
def test_torn_bag_is_recovered_up_to_the_last_complete_chunk(original, tmp_path, where):
    path, messages, summary = original
    data = path.read_bytes()
    cut = cut_points(summary, _footer_summary_start(path))[where]
    torn = tmp_path / 'torn.mcap'
    torn.write_bytes(data[:cut])
    assert unreadable_by_standard_readers(torn)
    with pytest.raises(BagCorruptError, match='recover'):
        message_counts(torn)

    report = recover(torn, tmp_path / 'rescued.mcap')
    want = expected_prefix(messages, summary, cut)
    assert report.truncated and not report.data_complete
    assert report.messages == len(want)
    got, rescued_summary = read_all(report.output)  # a finished, indexed file again
    assert got == want  # same topics, times and bytes
    assert rescued_summary.statistics.message_count == len(want)
    if want:
        assert sum(rosbags_counts(report.output).values()) == len(want)
        channels = {c.topic: c for c in rescued_summary.channels.values()}
        original_channels = {c.topic: c for c in summary.channels.values()}
        for topic, channel in channels.items():
            assert channel.metadata == original_channels[topic].metadata  # QoS + type hash kept


def test_torn_summary_loses_nothing(original, tmp_path):
    path, messages, summary = original
    data = path.read_bytes()
    # cut inside the summary section: after DataEnd every message is already on disk
    summary_start = _footer_summary_start(path)
    torn = tmp_path / 'torn_summary.mcap'
    torn.write_bytes(data[: summary_start + 20])
    assert unreadable_by_standard_readers(torn)
    report = recover(torn, tmp_path / 'rescued.mcap')
    assert report.truncated and report.data_complete
    assert read_all(report.output)[0] == messages


def _footer_summary_start(path):
    from mcap.records import Footer
    from mcap.stream_reader import StreamReader

    return next(r for r in StreamReader(str(path)).records if isinstance(r, Footer)).summary_start


def test_finished_bag_round_trips_unchanged(original, tmp_path):
    path, messages, _ = original
    report = recover(path, tmp_path / 'copy.mcap')
    assert not report.truncated and report.data_complete and report.bad_chunks == 0
    assert report.messages == N and report.topics == {
        '/com_estimator/beta': 100,
        '/wheel_effort_cmd': 300,
    }
    assert read_all(report.output)[0] == messages


def test_corrupted_chunk_in_the_middle_is_skipped_not_fatal(original, tmp_path):
    path, messages, summary = original
    data = bytearray(path.read_bytes())
    chunk = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[3]
    # flip bits in its compressed data
    data[chunk.chunk_start_offset + chunk.chunk_length - 10] ^= 0xFF
    damaged = tmp_path / 'damaged.mcap'
    damaged.write_bytes(bytes(data))
    report = recover(damaged, tmp_path / 'rescued.mcap')
    lost = {m for m in messages if chunk.message_start_time <= m[1] <= chunk.message_end_time}
    assert report.bad_chunks == 1 and not report.truncated
    assert read_all(report.output)[0] == [m for m in messages if m not in lost]


KILLED_WRITER = textwrap.dedent("""
    import sys, time
    from std_msgs.msg import Float64MultiArray
    from krang_bag.writer import BagWriter
    writer = BagWriter(sys.argv[1], chunk_size=2048)
    for i in range(int(sys.argv[2])):
        msg = Float64MultiArray(data=[float(i), 1.0, 2.0])
        writer.write_message('/wheel_effort_cmd', msg, 10**18 + i)
        writer.flush()
    print('written', flush=True)
    time.sleep(60)
""")


def test_writer_killed_with_sigkill_is_recovered(tmp_path):
    bag, sent = tmp_path / 'killed.mcap', 300
    proc = subprocess.Popen(
        [sys.executable, '-c', KILLED_WRITER, str(bag), str(sent)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == 'written'
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert unreadable_by_standard_readers(bag)

    report = recover(bag, tmp_path / 'rescued.mcap')
    got, _ = read_all(report.output)
    kept = len(got)
    assert report.truncated and report.messages == kept
    # Exactly the first `kept` messages, in order and intact; only the open chunk (< 2048 B) is
    # lost.
    for i, (topic, log_time, data) in enumerate(got):
        assert (topic, log_time) == ('/wheel_effort_cmd', 10**18 + i)
    from rclpy.serialization import deserialize_message

    assert [deserialize_message(d, Float64MultiArray).data[0] for _, _, d in got] == list(
        range(kept)
    )
    # message record: opcode, length, header fields, data
    per_message = len(got[0][2]) + 31
    assert 0 < kept and sent - kept <= 2048 // per_message + 1
    assert rosbags_counts(report.output) == {'/wheel_effort_cmd': kept}


def test_recover_errors(tmp_path, original):
    path = original[0]
    with pytest.raises(BagNotFoundError):
        recover(tmp_path / 'missing.mcap')
    junk = tmp_path / 'junk.mcap'
    junk.write_bytes(os.urandom(300))
    with pytest.raises(BagCorruptError):
        recover(junk, tmp_path / 'out.mcap')
    with pytest.raises(ValueError):
        recover(path, path)
    (tmp_path / 'exists.mcap').write_bytes(b'keep me')
    with pytest.raises(FileExistsError):
        recover(path, tmp_path / 'exists.mcap')
    assert (tmp_path / 'exists.mcap').read_bytes() == b'keep me'


def test_cli_recover(original, tmp_path, capsys):
    path, messages, summary = original
    torn = tmp_path / 'torn.mcap'
    torn.write_bytes(path.read_bytes()[: int(0.5 * path.stat().st_size)])
    out = tmp_path / 'rescued.mcap'
    assert bag_cli.main(['recover', str(torn), '--out', str(out), '--json']) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report['truncated'] and report['messages'] == len(read_all(out)[0]) > 0
    # no silent overwrite
    assert bag_cli.main(['recover', str(torn), '--out', str(out)]) == 1
    assert 'exists' in capsys.readouterr().err
    assert bag_cli.main(['recover', str(torn), '--out', str(out), '--force']) == 0
    assert 'tail truncated' in capsys.readouterr().out
    # default name beside it
    assert bag_cli.main(['recover', str(torn)]) == 0
    assert (tmp_path / 'torn.recovered.mcap').exists()
    assert bag_cli.main(['info', str(torn)]) == 1
    assert 'krang bag recover' in capsys.readouterr().err
