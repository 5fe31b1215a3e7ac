"""A node's configuration dataclass as its ROS parameters: the rclpy part over
krang_core.params."""

from __future__ import annotations

import array

from rcl_interfaces.msg import ParameterDescriptor

from krang_core.params import ParameterError, build, leaves


def declare(node, cls, prefix: str = ''):
    """Declare every parameter of ``cls`` on ``node`` (default, description; read only: the nodes
    read their configuration once, at start, so a change at run time is refused with that reason)
    and build ``cls`` from their values.

    The ROS type is not enforced by rclpy (dynamic typing) but by ``build``, so that ``rate_hz:
    100`` in a YAML file is the float 100.0 rather than an InvalidParameterTypeException, and a
    wrong type or range is a ParameterError naming the parameter."""
    values = {}
    for leaf in leaves(cls):
        default = list(leaf.default) if leaf.kind is tuple else leaf.default
        descriptor = ParameterDescriptor(
            name=prefix + leaf.name, description=leaf.doc, read_only=True, dynamic_typing=True
        )
        value = node.declare_parameter(prefix + leaf.name, default, descriptor).value
        values[leaf.name] = list(value) if isinstance(value, (tuple, array.array)) else value
    try:
        return build(cls, values)
    except (TypeError, ValueError) as err:
        raise ParameterError(f'{node.get_name()}: {err}') from None
