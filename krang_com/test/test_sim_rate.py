"""--rate-hz: the simulated node set at another sample and control rate (500 Hz: the robot's).
One function gives the four parameters that move together; a bad rate is one line and exit 2
before anything starts; the composed `krang demo --rate-hz 500` stands the robot up, learns and
records /imu/data at 500 Hz of simulated time (slow: 40 s of wall time, 2.5x the default rate)."""

import json
import random
import subprocess
import sys
import time

import pytest

from conftest import REPO
from krang_model.config import load_config
from krang_sim.session_config import (
    PRIVATE_PORT_MIN,
    _ephemeral_port_min,
    private_port,
    rate_overrides,
    sim_rate_hz,
)


def test_500_hz_moves_the_samples_the_clock_the_imu_period_and_the_control_step():
    assert rate_overrides(500) == {
        'sim_krang': {'feedback_rate_hz': 500.0, 'clock_rate_hz': 500.0},
        'can_bridge': {'imu_sample_period_s': pytest.approx(0.002)},
        'adrc_controller': {'rate_hz': 500.0},
    }


def test_no_rate_is_the_configured_one_and_the_file_agrees_with_it():
    assert rate_overrides(None) == {}
    config = load_config('sim_params.yaml')
    for node, params in rate_overrides(sim_rate_hz()).items():
        for name, value in params.items():
            assert config[node]['ros__parameters'][name] == pytest.approx(value), (node, name)


@pytest.mark.parametrize('rate', [0, -500, 300, 2000, float('nan')])
def test_a_rate_that_is_not_positive_or_does_not_divide_the_physics_rate_is_refused(rate):
    with pytest.raises(ValueError, match='Hz') as err:
        rate_overrides(rate)
    assert '\n' not in str(err.value)


def krang(*args, cwd):
    proc = subprocess.run(
        [sys.executable, '-m', 'krang_cli.main', *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )
    return proc.returncode, (proc.stdout + proc.stderr).strip()


@pytest.mark.parametrize(
    'args, says',
    [
        (('demo', '--rate-hz', '0', '--out', 'out'), '--rate-hz 0 Hz'),
        (('demo', '--rate-hz', '300', '--out', 'out'), '--rate-hz 300 Hz'),
        (('bringup', '--rate-hz', '500'), 'need --sim'),
        (('bringup', '--sim', '--rate-hz', '-1'), '--rate-hz -1 Hz'),
    ],
)
def test_a_bad_rate_on_the_command_line_is_one_line_and_exit_2(args, says, tmp_path):
    code, out = krang(*args, cwd=tmp_path)
    assert code == 2 and 'Traceback' not in out and len(out.splitlines()) == 1, out
    assert says in out, out
    assert not (tmp_path / 'out').exists()  # refused before the demo writes anything


def test_bringup_sim_gives_the_nodes_the_rate_beside_the_plant(monkeypatch):
    from krang_cli import bringup
    from krang_cli.main import build_parser

    started = {}

    class Nodes:
        def stop(self, order):
            pass

    def start_node_set(sim, extra_params=(), record=None, log_dir=None, overrides=None):
        started.update(sim=sim, overrides=overrides)
        return Nodes()

    monkeypatch.setattr(bringup, 'start_node_set', start_node_set)
    monkeypatch.setattr(bringup, 'wait_forever', lambda nodes: 0)
    args = build_parser().parse_args(['bringup', '--sim', '--plant', 'mujoco', '--rate-hz', '500'])
    assert args.func(args) == 0 and started['sim']
    rates = rate_overrides(500)
    assert started['overrides'] == {
        **rates,
        'sim_krang': {**rates['sim_krang'], 'plant': 'mujoco'},
    }


def imu_rate_over_clock_span(bag):
    """/imu/data messages per simulated second over the span /clock covers, and the rate of
    their header stamps."""
    from krang_bag.reader import iter_messages
    from krang_core import names

    clock, imu = [], []
    for topic, _, msg in iter_messages(bag, [names.CLOCK, names.IMU]):
        if topic == names.CLOCK:
            clock.append(msg.clock.sec + msg.clock.nanosec * 1e-9)
        else:
            imu.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
    start, end = min(clock), max(clock)
    within = [t for t in imu if start <= t <= end]
    return len(within) / (end - start), (len(imu) - 1) / (max(imu) - min(imu))


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_composed_demo_at_500_hz_stands_learns_and_samples_at_500_hz(tmp_path):
    out = tmp_path / 'demo'
    started = time.monotonic()
    proc = subprocess.run(
        [
            sys.executable,
            '-m',
            'krang_cli.main',
            'demo',
            '--rate-hz',
            '500',
            '--poses',
            '1',
            '--out',
            str(out),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=540,
    )
    wall = time.monotonic() - started
    logs = ''.join(p.read_text()[-1500:] for p in sorted((out / 'logs').glob('*.log')))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:] + logs
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f'krang demo --rate-hz 500 --poses 1: {wall:.0f} s wall, {summary}')
    assert summary['poses'] == 1 and summary['rate_hz'] == 500
    assert summary['com_error_after_m'] < summary['com_error_before_m']
    assert '500 Hz' in (out / 'report.md').read_text()
    over_clock, stamps = imu_rate_over_clock_span(out / 'session.mcap')
    assert over_clock == pytest.approx(500, rel=0.05)
    assert stamps == pytest.approx(500, rel=0.05)


def test_private_ports_stay_clear_of_dds_and_the_ephemeral_range():
    """A session's bus ports (16 from the one drawn) lie below the kernel's ephemeral range and
    off every DDS (RTPS) discovery and user port of domains 0-232 with up to 60 participants:
    7400 + 250 d + {0, 1, 10, 11} + 2 p. A udp_multicast bus that landed on a port another
    program held without SO_REUSEPORT did not open."""
    rtps = {
        7400 + 250 * d + o + 2 * p for d in range(233) for o in (0, 1, 10, 11) for p in range(60)
    }
    rng = random.Random(0)
    for _ in range(2000):
        port = private_port(rng=rng)
        block = set(range(port, port + 16))
        assert PRIVATE_PORT_MIN <= port and port + 16 <= _ephemeral_port_min()
        assert not block & rtps, port
