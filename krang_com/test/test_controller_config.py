"""The controller's configuration: nested dataclasses <-> dotted ROS parameters
(krang_core/params.py, without ROS), and the parameter files that set them."""

from dataclasses import dataclass, field

import pytest
import yaml

from krang_adrc_controller.controller import NODE_NAME, ControllerConfig, load_controller_config
from krang_model.config import config_path
from krang_core import params
from krang_ros.realtime import SchedulingParams


@dataclass(frozen=True)
class Inner:
    gain: float = field(default=2.0, metadata={'doc': 'a gain'})
    count: int = 3
    on: bool = True


@dataclass(frozen=True)
class Outer:
    name: str = 'x'
    weights: tuple[float, ...] = (1.0, 2.0)
    inner: Inner = Inner()


def test_flatten_uses_dotted_names_and_lists():
    assert params.flatten(Outer()) == {
        'name': 'x',
        'weights': [1.0, 2.0],
        'inner.gain': 2.0,
        'inner.count': 3,
        'inner.on': True,
    }


def test_round_trip():
    cfg = Outer(name='y', weights=(3.0,), inner=Inner(gain=-1.5, count=7, on=False))
    assert params.build(Outer, params.flatten(cfg)) == cfg
    full = ControllerConfig().override(
        {'adrc.eso.omega_o': 7.0, 'modes.stand_gains': [1, 2, 3, 4, 5, 6]}
    )
    assert params.build(ControllerConfig, params.flatten(full)) == full
    assert full.adrc.eso.omega_o == 7.0
    assert full.modes.stand_gains == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)


def test_missing_names_keep_the_defaults_or_the_base():
    assert params.build(Outer, {}) == Outer()
    base = Outer(name='base')
    got = params.override(base, {'inner.count': 9})
    assert got == Outer(name='base', inner=Inner(count=9))


def test_unknown_names_are_rejected():
    with pytest.raises(ValueError, match=r"unknown Outer parameters: \['inner.gian'\]"):
        params.build(Outer, {'inner.gian': 1.0})
    with pytest.raises(ValueError, match='unknown'):
        params.build(Outer, {'inner': 1.0})  # a group is not a parameter
    with pytest.raises(ValueError, match='unknown'):
        load_controller_config(overrides={'no_such_gain': 1.0})


@pytest.mark.parametrize(
    'name,value',
    [
        ('inner.gain', 'fast'),
        ('inner.gain', True),
        ('inner.count', 2.5),
        ('inner.count', False),
        ('inner.on', 1),
        ('name', 3),
        ('weights', 1.0),
        ('weights', ['a']),
    ],
)
def test_types_are_checked(name, value):
    with pytest.raises(TypeError, match=name):
        params.build(Outer, {name: value})


def test_an_int_is_a_float_and_ranges_are_the_dataclasses():
    got = params.build(Outer, {'inner.gain': 4})
    assert got.inner.gain == 4.0 and isinstance(got.inner.gain, float)
    with pytest.raises(ValueError, match='rate_hz'):
        ControllerConfig().override({'rate_hz': -1.0})
    with pytest.raises(ValueError, match='stand_gains'):
        ControllerConfig().override({'modes.stand_gains': [1.0, 2.0]})


def test_leaves_carry_type_default_and_description():
    leaves = {leaf.name: leaf for leaf in params.leaves(Outer)}
    assert list(leaves) == ['name', 'weights', 'inner.gain', 'inner.count', 'inner.on']
    assert leaves['inner.gain'] == params.Leaf('inner.gain', float, 2.0, 'a gain')
    assert leaves['weights'].kind is tuple and leaves['inner.count'].kind is int
    # every controller parameter is documented for `ros2 param describe`
    undocumented = [leaf.name for leaf in params.leaves(ControllerConfig) if not leaf.doc]
    assert undocumented == []


def test_nested_yaml_reads_as_dotted():
    doc = {'rate_hz': 100.0, 'adrc': {'eso': {'omega_o': 10.0}}, 'safety.stale_timeout_s': 0.5}
    assert params.nested_to_dotted(doc) == {
        'rate_hz': 100.0,
        'adrc.eso.omega_o': 10.0,
        'safety.stale_timeout_s': 0.5,
    }


def _controller_section(name):
    doc = yaml.safe_load(config_path(name).read_text())
    return params.nested_to_dotted(doc[NODE_NAME]['ros__parameters'] or {})


#: the node's own parameters, not the controller's (node.py; its scheduling: realtime.py), and
#: ROS's
NODE_PARAMETERS = {
    'use_sim_time',
    'step_on_imu',
    'initial_beta',
    *(leaf.name for leaf in params.leaves(SchedulingParams)),
}


@pytest.mark.parametrize('name', ['controller.yaml', 'sim_params.yaml'])
def test_parameter_files_name_only_controller_parameters(name):
    """Every key of the parameter files is a ControllerConfig parameter with a value of its type,
    and none merely repeats its default (the files hold what differs)."""
    values = {k: v for k, v in _controller_section(name).items() if k not in NODE_PARAMETERS}
    params.build(ControllerConfig, values)
    defaults = params.flatten(ControllerConfig())
    assert [k for k, v in values.items() if defaults[k] == v] == []


def test_shipped_configuration_is_the_defaults():
    assert load_controller_config() == ControllerConfig()
