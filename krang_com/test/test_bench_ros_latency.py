"""bench/bench_ros_latency.py: the matching of wheel commands to sensor samples (its analysis,
ros_latency_analysis.py, on synthetic frame times), the device player's schedule, and a short
--robot run (ros, slow) that must print its figures as JSON (and, --trace, the segments of its
latency)."""

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import can
import numpy as np
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('msgpack')  # python-can's udp_multicast needs it

from krang_cli.node_set import file_parameter  # noqa: E402
from krang_sim.devices import BusFrame  # noqa: E402

BENCH = Path(__file__).resolve().parents[2] / 'bench' / 'bench_ros_latency.py'
PERIOD = 0.002


def _load(path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope='module')
def bench():
    """The benchmark's analysis (ros_latency_analysis.py, plain numpy)."""
    return _load(BENCH.parent / 'ros_latency_analysis.py')


@pytest.fixture(scope='module')
def player():
    return _load(BENCH.parent / 'device_player.py')


def test_the_player_plays_late_periods_in_order_and_skips_only_a_long_stall(player):
    """A device never drops a period: after a stall shorter than CATCH_UP_PERIODS every missed
    period is still played, at once and in order; after a longer one the missed ones are skipped
    and the next is due after the stall."""
    n = player.CATCH_UP_PERIODS

    def play(stall_periods, periods=100):
        """Periods played in `periods` of time by a loop that stalls once, at period 10."""
        due, now, count = 0.0, 0.0, 0
        while due < periods * PERIOD:
            now = max(now, due)
            if count == 10:
                now += stall_periods * PERIOD
            count += 1
            due = player.next_due(due, PERIOD, now)
        return count

    assert play(0) == 100
    assert play(n - 0.5) == 100  # all played, the late ones in a burst
    assert play(n + 3.5) < 100  # a long stall: the periods it missed are skipped
    assert player.next_due(0.0, PERIOD, (n + 3.5) * PERIOD) > (n + 3.5) * PERIOD


def test_the_wire_carries_one_frame_at_a_time_per_bus(player):
    """At 1 Mbit/s an 8-byte standard frame occupies 111 bit times (47 + 64; CAN 2.0A without
    stuff bits) and an extended one 131: a set of frames on one bus goes out that far apart, a
    frame on another bus at once, a frame after the bus went idle at once, and at bit rate 0 all
    at once."""

    def frame(bus, n=8, extended=False):
        return BusFrame(
            bus, can.Message(arbitration_id=0x181, data=bytes(n), is_extended_id=extended)
        )

    assert player.frame_bits(frame('a').msg) == 111
    assert player.frame_bits(frame('a', 2, extended=True).msg) == 67 + 16
    wire = player.Wire(1e6)
    a1, a2, a3, b1 = frame('a'), frame('a', 4), frame('a', 0, extended=True), frame('b')
    wire.add([a1, a2, a3, b1], now=10.0)
    assert wire.take(10.0) == [a1, b1]
    assert wire.due() == pytest.approx(10.0 + 111e-6)
    assert wire.take(10.0 + 110e-6) == []
    assert wire.take(10.0 + 112e-6) == [a2]
    assert wire.due() == pytest.approx(10.0 + 111e-6 + 79e-6)
    assert wire.take(11.0) == [a3]
    assert wire.due() == float('inf')
    wire.add([a1], now=12.0)  # the bus has been free since 10.000257
    assert wire.take(12.0) == [a1]
    burst = player.Wire(0)
    burst.add([a1, a2, a3], now=1.0)
    assert burst.take(1.0) == [a1, a2, a3]


def played(n=2000, latency=0.003, probe_every=5, response=900.0, noise=10.0, seed=1):
    """Samples every PERIOD, from sample 500 on every probe_every-th one a probe of alternating
    sign (its command +-response, the others -+response/(probe_every-1)), each answered
    `latency` later and repeated by a refresh 0.5 ms after that."""
    rng = np.random.default_rng(seed)
    t = 100.0 + PERIOD * np.arange(n)
    k = np.arange(n) - 500
    sign = np.where((k // probe_every) % 2 == 0, 1.0, -1.0)
    phase0 = k % probe_every == 0
    kick = sign * np.where(phase0, response, -response / (probe_every - 1))
    kick[k < 0] = 0.0
    probe = np.where(phase0 & (k >= 0), sign, 0).astype(np.int8)
    value = -200.0 + kick + rng.normal(0.0, noise, n)  # no two alike
    cmd_t = np.concatenate([t + latency, t + latency + 0.0005])
    cmd_v = np.concatenate([value, value])
    return t, probe, cmd_t, cmd_v


def test_refreshes_are_not_answers(bench):
    t, v = bench.new_commands([3.0, 1.0, 2.0, 4.0], [5, 5, 5, 6])
    assert list(t) == [1.0, 4.0] and list(v) == [5, 6]


def test_timing_reads_short_when_the_answer_comes_after_the_next_sample(bench):
    t, probe, cmd_t, cmd_v = played(latency=0.0013)
    ct, _ = bench.new_commands(cmd_t, cmd_v)
    lat, answered = bench.timing_match(t, ct)
    assert np.allclose(lat, 0.0013) and answered == len(t)
    t, probe, cmd_t, cmd_v = played(latency=0.0031)
    lat, _ = bench.timing_match(t, bench.new_commands(cmd_t, cmd_v)[0])
    assert np.allclose(lat, 0.0011)  # 3.1 ms read as 3.1 - 2 ms


def test_probes_carry_the_sample_identity(bench):
    t, probe, cmd_t, cmd_v = played(latency=0.0031)
    ct, cv = bench.new_commands(cmd_t, cmd_v)
    lat, response, at = bench.probe_match(t, probe, ct, cv)
    assert response == pytest.approx(0.75 * 900.0, abs=50.0)  # from the last compensation
    assert len(lat) == np.count_nonzero(probe) and np.allclose(lat, 0.0031)
    assert np.array_equal(at, t[probe != 0])  # each latency with its probe's sample
    assert bench.noise_level(ct, cv, t[probe != 0][0]) == pytest.approx(10.0, rel=0.3)


def test_dropped_probe_samples_are_not_answered(bench):
    t, probe, cmd_t, cmd_v = played(latency=0.0025)
    keep = np.ones(len(cmd_t), bool)
    lost = np.flatnonzero(probe > 0)  # the positive probes never answered
    keep[lost] = keep[lost + len(t)] = False
    ct, cv = bench.new_commands(cmd_t[keep], cmd_v[keep])
    lat, _, at = bench.probe_match(t, probe, ct, cv)
    assert len(lat) == np.count_nonzero(probe) - len(lost) and np.allclose(lat, 0.0025)
    assert np.array_equal(at, t[probe < 0])  # the negative probes, the only ones answered


def test_reference_pairs_frames_by_counter(bench):
    req = np.array([[1.0, 7], [1.002, 8], [1.004, 9], [5.0, 10]])
    ans = np.array([[1.0011, 7], [1.0052, 9]])
    lat, lost, at = bench.reference_latencies(req, ans, (0.5, 2.0))
    assert np.allclose(lat, [0.0011, 0.0012]) and lost == 1 and list(at) == [1.0, 1.004]
    lat, lost, at = bench.reference_latencies(req, ans, (3.0, 6.0))  # none answered
    assert len(lat) == len(at) == 0 and lost == 1


def test_p50_by_next_tpdo_places_each_sample_by_the_tpdo_set_after_it(bench):
    """TPDO sets drifting through the whole period; a sample whose next set comes 0.4-0.8 ms
    after it (the second fifth of 2 ms) waits 0.5 ms more: the medians per part are the latencies
    set for it, placed by the drift alone."""
    t = 100.0 + PERIOD * np.arange(5000)
    tpdo = t + PERIOD * np.linspace(1.0, 0.0, len(t), endpoint=False)  # next set: 1 -> 0 periods
    after = tpdo - t
    lat = np.where((after >= 0.0004) & (after < 0.0008), 0.0015, 0.0010)
    parts = bench.p50_by_next_tpdo(t, lat, tpdo, PERIOD)
    assert parts == pytest.approx([1.0, 1.5, 1.0, 1.0, 1.0])
    # a sample after the last set has no next one: left out; a part without samples is nan
    parts = bench.p50_by_next_tpdo(t[:10], lat[:10], tpdo[:5], PERIOD)
    assert np.isnan(parts[0]) and not np.isnan(parts[-1])


def test_tpdo_phases_seen_tells_a_sweeping_phase_from_a_fixed_one(bench):
    """TPDO sets half a period after each sample: one tenth of the period; drifting by a full
    period over the window (what --tpdo-drift-ppm does over a measurement): all ten."""
    t = 100.0 + PERIOD * np.arange(1000)
    window = (t[0], t[-1])
    fixed = t + 0.5 * PERIOD
    drifting = t + 0.5 * PERIOD + np.linspace(0.0, PERIOD, len(t), endpoint=False)
    assert bench.tpdo_phases_seen(t, fixed, window) == pytest.approx(0.1)
    assert bench.tpdo_phases_seen(t, drifting, window) == pytest.approx(1.0)
    assert np.isnan(bench.tpdo_phases_seen(t, fixed, (0.0, 1.0)))  # none in the window


def test_analyse_gives_the_json_keys_first(bench):
    t, probe, cmd_t, cmd_v = played(latency=0.0031)
    record = {
        'sample_t': t,
        'sample_probe': probe,
        'sample_late': np.where(np.arange(len(t)) % 100 == 0, 0.0025, 0.0001),
        'cmd_t': cmd_t,
        'cmd_id': np.full(len(cmd_t), 0x220),
        'cmd_value': cmd_v,
        'left_id': 0x220,
        'ref_req': np.column_stack([t, np.arange(len(t))]),
        'ref_ans': np.column_stack([t + 0.001, np.arange(len(t))]),
        'tpdo_t': t[::2] + 0.001,  # TPDO sets every second sample: 250 Hz
    }
    # the controller's 1 Hz reports (stamp, samples_stepped, samples_superseded): 490 steps/s,
    # 20 of them superseded; one report before the window, which must not count
    reports = [(t[0] + 0.5 * k, 245 * k + (1000 if k == 0 else 0), 10 * k) for k in range(9)]
    # the bridge's (stamp, /imu/data published): 496 a second
    published = [(t[0] + 0.5 * k, 248 * k) for k in range(9)]
    window = (t[600], t[-20])
    fig = bench.analyse(record, window, 500.0, reports, bridge_diag=published)
    assert tuple(fig)[:6] == bench.JSON_KEYS
    assert fig['match'] == 'probe' and fig['p50_ms'] == pytest.approx(3.1, abs=1e-6)
    assert fig['rate_hz'] == pytest.approx(490.0, rel=1e-9)
    assert fig['superseded_hz'] == pytest.approx(20.0, rel=1e-9)
    assert fig['bus_rate_hz'] == pytest.approx(500.0, rel=0.01)
    assert fig['ref_p50_ms'] == pytest.approx(1.0, abs=1e-6)
    assert fig['ref_frames'] == 1981 - 600  # the reference frames of the window only
    assert fig['tpdo_rate_hz'] == pytest.approx(250.0, rel=0.01)
    assert fig['bridge_imu_rate_hz'] == pytest.approx(496.0, rel=1e-9)
    # one sample in a hundred sent 2.5 ms late, over the 2 ms period: 5 a second
    assert fig['dmu_late_hz'] == pytest.approx(5.0, rel=0.02)
    assert fig['dmu_max_late_ms'] == pytest.approx(2.5)
    # the reference measured in a window of its own (before the nodes start)
    ref_only = bench.analyse(record, window, 500.0, reports, ref_window=(t[0], t[99]))
    assert ref_only['ref_frames'] == 100 and ref_only['p50_ms'] == fig['p50_ms']
    assert ref_only['ref_tpdo_rate_hz'] == pytest.approx(250.0, rel=0.03)


@pytest.mark.ros
@pytest.mark.slow
def test_robot_run_prints_the_figures_as_json():
    env = dict(
        os.environ,
        ROS_DOMAIN_ID=str(100 + os.getpid() % 80),
        ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
    )
    run = subprocess.run(
        [
            sys.executable,
            str(BENCH),
            '--robot',
            '--seconds',
            '3',
            '--json',
            '--tpdo-period-ms',
            '4',
            '--trace',
        ],
        capture_output=True,
        text=True,
        timeout=280,
        env=env,
        cwd=BENCH.parents[1],
    )
    assert run.returncode == 0, run.stderr[-3000:]
    fig = json.loads(run.stdout.strip().splitlines()[-1])
    assert list(fig)[:6] == [
        'p50_ms',
        'p99_ms',
        'rate_hz',
        'configured_rate_hz',
        'ref_p50_ms',
        'ref_p99_ms',
    ]
    assert fig['configured_rate_hz'] == 500.0
    assert fig['ref_p50_ms'] > 0.0 and fig['ref_p99_ms'] >= fig['ref_p50_ms']
    assert fig['p50_ms'] > 0.0 and fig['rate_hz'] > 0.0
    # the bench's map told the bridge 4 ms, the bridge the drives, and the player followed them
    # (stand-in drives at the map's period beside the reference); a period skipped after a stall
    # of the loaded machine is the only loss
    assert fig['tpdo_period_ms'] == 4
    assert fig['tpdo_drift_ppm'] == 100.0 and 0.0 < fig['tpdo_phases_seen'] <= 1.0
    assert fig['bus_bitrate'] == 1e6  # the players' frames spaced as Krang's nets carry them
    assert len(fig['p50_by_next_tpdo_ms']) == len(fig['ref_p50_by_next_tpdo_ms']) == 5
    assert 200.0 < fig['tpdo_rate_hz'] <= 251.0 and 200.0 < fig['ref_tpdo_rate_hz'] <= 251.0
    # the DMU's player (a process of its own) plays every period, late ones late, and the bridge
    # publishes a sample for each (over 3 s the 1 Hz counts are whole seconds: +-1 sample)
    assert 495.0 < fig['dmu_rate_hz'] < 505.0
    assert 490.0 < fig['bridge_imu_rate_hz'] < 510.0
    # --trace: the samples joined across both nodes on their stamps, each stage after the one
    # before, and the sample's traced path (its frame in the bridge's kernel to both current
    # frames sent) of the order of what the player measured on the bus (the first current frame)
    trace = fig['trace_p50_ms']
    assert fig['traced_samples'] > 500
    assert all(v > 0.0 for v in trace.values()), trace
    assert 0.5 * fig['p50_ms'] < trace['total'] < 2.0 * fig['p50_ms'], (trace, fig['p50_ms'])
    # the nodes ran at the robot's thread_priority, set by themselves (krang_ros/realtime.py)
    assert fig['thread_priority'] == file_parameter('can_bridge', 'thread_priority', sim=False)
    if os.geteuid() == 0:
        assert {'can_bridge', 'adrc_controller', 'DMU player', 'device player'} <= set(
            fig['real_time'].split(', ')
        ), fig['real_time']
