"""Parameters as a ROS node sees them (krang_ros/params.declare): descriptors, an int where a float
is declared, a run-time change refused with a reason, an invalid start value named in one line."""

import subprocess
import sys
from dataclasses import dataclass, field

import pytest

from krang_core.params import ParameterError
from krang_ros.params import declare

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip('rclpy')
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402


@dataclass(frozen=True)
class Config:
    rate_hz: float = field(default=200.0, metadata={'doc': 'loop rate [Hz], > 0'})
    method: str = field(default='map', metadata={'doc': 'map | gd'})
    topics: tuple[str, ...] = field(default=(), metadata={'doc': 'names'})

    def __post_init__(self):
        if not self.rate_hz > 0:
            raise ValueError(f'rate_hz must be > 0, got {self.rate_hz}')
        if self.method not in ('map', 'gd'):
            raise ValueError(f'method must be map or gd, got {self.method!r}')


def make_node(context, **overrides):
    return Node(
        'params_probe',
        context=context,
        parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
    )


def test_descriptors_int_for_float_and_string_lists(context):
    node = make_node(context, rate_hz=100, topics=['/a', '/b'])
    cfg = declare(node, Config)
    assert cfg == Config(rate_hz=100.0, topics=('/a', '/b'))
    d = node.describe_parameter('rate_hz')
    assert d.description == 'loop rate [Hz], > 0' and d.read_only
    node.destroy_node()


def test_run_time_change_is_refused_with_a_reason(context):
    node = make_node(context)
    declare(node, Config)
    result = node.set_parameters([Parameter('method', value='bogus')])[0]
    assert not result.successful and 'read-only' in result.reason
    assert node.get_parameter('method').value == 'map'
    node.destroy_node()


@pytest.mark.parametrize(
    'name, value, message',
    [
        ('rate_hz', 0.0, 'rate_hz must be > 0'),
        ('method', 'bogus', 'method must be map or gd'),
        ('rate_hz', 'fast', 'rate_hz must be float'),
    ],
)
def test_invalid_start_values_are_one_parameter_error(context, name, value, message):
    node = make_node(context, **{name: value})
    with pytest.raises(ParameterError, match=message):
        declare(node, Config)
    node.destroy_node()


def test_node_with_an_invalid_parameter_exits_with_one_line(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            '-m',
            'krang_ros.entry',
            'mcap_recorder',
            '--ros-args',
            '-p',
            'poll_period_s:=0.0',
            '-p',
            f'output:={tmp_path / "x.mcap"}',
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert out.returncode == 2
    assert out.stderr.strip() == 'error: mcap_recorder: poll_period_s must be > 0, got 0.0'
    assert not (tmp_path / 'x.mcap').exists()
