"""krang_ros.trace: the stage lines the nodes write under KRANG_TRACE, read back and split into the
segments of each sample's latency (synthetic times with known segments)."""

import os
import subprocess
import sys
from types import SimpleNamespace

import pytest

from krang_ros import trace


def stamp(t):
    sec = int(t)
    return SimpleNamespace(sec=sec, nanosec=round((t - sec) * 1e9))


def test_off_without_the_environment_variable():
    env = {k: v for k, v in os.environ.items() if k != trace.ENV}
    out = subprocess.run(
        [sys.executable, '-c', 'from krang_ros import trace; print(trace.ON)'],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    assert out.stdout.strip() == 'False'


def test_each_process_writes_its_own_file_read_back_exactly(tmp_path):
    prefix = tmp_path / 'trace'
    code = (
        'from types import SimpleNamespace as S\n'
        'from krang_ros import trace\n'
        'assert trace.ON\n'
        "trace.record('imu_in', S(sec=100, nanosec=2_000_000), 100.001, 100.0015, 100.0019)\n"
        "trace.record('step', S(sec=100, nanosec=2_000_000), 100.0023, 100.0027)\n"
        "trace.record('cmd_out', S(sec=100, nanosec=2_000_000), 100.0031, 100.0034)\n"
    )
    env = dict(os.environ, **{trace.ENV: str(prefix)})
    for _ in range(2):
        subprocess.run([sys.executable, '-c', code], env=env, check=True)
    files = sorted(tmp_path.glob('trace.*'))
    assert len(files) == 2  # <prefix>.<pid>, one per process
    traced = trace.read(map(str, files))
    assert traced['imu_in'] == {100.002: (100.001, 100.0015, 100.0019)}
    assert traced['step'] == {100.002: (100.0023, 100.0027)}
    assert traced['cmd_out'] == {100.002: (100.0031, 100.0034)}


def test_segments_of_each_sample_add_up_to_its_total():
    # sample k: frame at t0, then the six segments' durations d (known), in the stages' order
    durations = [0.0004, 0.0003, 0.0005, 0.0002, 0.0006, 0.0001]
    traced = {s: {} for s in trace.STAGES}
    for k in range(10):
        t0 = 1000.0 + 0.002 * k
        t = [t0]
        for d in durations:
            t.append(t[-1] + d * (1 + k / 10))  # every sample a little slower
        key = stamp(t0 - 0.0001)
        key = key.sec + key.nanosec * 1e-9
        traced['imu_in'][key] = (t[0], t[1], t[2])
        traced['step'][key] = (t[3], t[4])
        traced['cmd_out'][key] = (t[5], t[6])
    traced['cmd_out'][12345.0] = (1.0, 2.0)  # a command for a sample never traced in: not joined
    seg = trace.segments(traced, 1000.0, 1000.0 + 0.002 * 4)  # samples 0..4
    assert len(seg['total']) == 5
    for (name, _, _), d in zip(trace.SEGMENTS, durations):
        assert seg[name] == pytest.approx([d * (1 + k / 10) for k in range(5)], abs=1e-9)
    for k in range(5):
        assert sum(seg[name][k] for name, _, _ in trace.SEGMENTS) == pytest.approx(
            seg['total'][k], abs=1e-9
        )


def test_a_second_command_for_the_same_sample_is_not_its_answer(tmp_path):
    path = tmp_path / 'trace.1'
    path.write_text(
        'cmd_out 5.0 5.1 5.2\n'
        'cmd_out 5.0 5.3 5.4\n'  # a timer's repeat of the last stamp
        'step 5.0 5.05\n'  # malformed: a time missing
        'unknown 5.0 1 2\n'
    )
    traced = trace.read([str(path)])
    assert traced['cmd_out'] == {5.0: (5.1, 5.2)}
    assert traced['step'] == {} and traced['imu_in'] == {}


def test_two_threads_of_one_process_write_whole_lines(tmp_path):
    # can_bridge records from its receive thread and its executor's at once
    prefix = tmp_path / 'trace'
    code = (
        'import threading\n'
        'from types import SimpleNamespace as S\n'
        'from krang_ros import trace\n'
        'def write(stage, n):\n'
        '    for k in range(20000):\n'
        '        trace.record(stage, S(sec=k, nanosec=0), *([k + 0.125] * n))\n'
        'threads = [\n'
        '    threading.Thread(target=write, args=(s, n)) for s, n in trace.STAGES.items()\n'
        ']\n'
        'for t in threads: t.start()\n'
        'for t in threads: t.join()\n'
    )
    subprocess.run(
        [sys.executable, '-c', code], env=dict(os.environ, **{trace.ENV: str(prefix)}), check=True
    )
    (path,) = tmp_path.glob('trace.*')
    lines = path.read_bytes().decode().splitlines()
    assert len(lines) == 3 * 20000
    traced = trace.read([str(path)])
    for stage, n in trace.STAGES.items():
        assert traced[stage] == {float(k): (k + 0.125,) * n for k in range(20000)}


def test_a_line_cut_short_is_skipped(tmp_path):
    path = tmp_path / 'trace.2'
    path.write_bytes(b'step 1.0 1.1 1.2\nstep 2.0 2.1 2.\xf1\nimu_in 3.0 3.1 3.2 3')
    traced = trace.read([str(path)])
    assert traced['step'] == {1.0: (1.1, 1.2)}
    assert traced['imu_in'] == {}  # the last line, no newline: its last time may be cut
