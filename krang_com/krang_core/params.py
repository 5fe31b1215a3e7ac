"""Nested, frozen configuration dataclasses as dotted ROS parameters.

A node's configuration is one frozen dataclass whose fields are plain values (bool, int, float,
str, tuple of floats) or further such dataclasses. Each leaf is one ROS parameter named by its
path, ``observer.bandwidth`` for ``cfg.observer.bandwidth``: the ROS convention for nested
parameters, so a YAML file may write them nested or dotted. A field's description is its
``metadata['doc']``.

Plain Python, so configurations are built and tested without ROS; krang_ros.params.declare makes
them a node's parameters.
"""

from __future__ import annotations

import array
import dataclasses
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


class ParameterError(ValueError):
    """A node's parameters are invalid (unknown name, wrong type, out of range): the node reports
    it in one line and exits instead of running half-configured."""


@dataclass(frozen=True)
class Leaf:
    """One parameter: its dotted name, value type (bool, int, float, str or tuple), default and
    description; ``item`` is a tuple's element type (float or str)."""

    name: str
    kind: type
    default: Any
    doc: str
    item: type = float


def leaves(cls, prefix: str = '') -> list[Leaf]:
    """Every parameter of the configuration class ``cls``, depth first in field order."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        name = prefix + f.name
        kind = hints[f.name]
        if dataclasses.is_dataclass(kind):
            out += leaves(kind, name + '.')
            continue
        item = (typing.get_args(kind) or (float,))[0]
        kind = typing.get_origin(kind) or kind
        if kind not in (bool, int, float, str, tuple) or item not in (float, str):
            raise TypeError(
                f'{name}: parameters are bool, int, float, str or a tuple of float or '
                f'str, not {kind}'
            )
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        out.append(Leaf(name, kind, default, f.metadata.get('doc', ''), item))
    return out


def describe(cls, prefix: str = '') -> list[str]:
    """One line per parameter, 'name (type, default): description', for a node's --help."""

    def type_name(leaf):
        return f'list of {leaf.item.__name__}' if leaf.kind is tuple else leaf.kind.__name__

    return [
        f'{prefix}{leaf.name} ({type_name(leaf)}, {leaf.default!r}): {leaf.doc}'
        for leaf in leaves(cls)
    ]


def flatten(config) -> dict[str, Any]:
    """{dotted name: value} of a configuration; tuples become lists (ROS arrays)."""
    out = {}
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        if dataclasses.is_dataclass(v):
            out.update({f'{f.name}.{k}': w for k, w in flatten(v).items()})
        else:
            out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


def _coerce(leaf: Leaf, v):
    """The value as the field's type; TypeError when it is not one (an int is a float, a bool is
    neither an int nor a float)."""
    k = leaf.kind
    ok = (
        isinstance(v, bool)
        if k is bool
        else isinstance(v, int) and not isinstance(v, bool)
        if k is int
        else isinstance(v, (int, float)) and not isinstance(v, bool)
        if k is float
        else isinstance(v, str)
        if k is str
        else isinstance(v, (list, tuple, array.array))
        and all(
            isinstance(e, str)
            if leaf.item is str
            else isinstance(e, (int, float)) and not isinstance(e, bool)
            for e in v
        )
    )
    if not ok:
        of = {float: ' of numbers', str: ' of strings'}[leaf.item] if k is tuple else ''
        raise TypeError(f'parameter {leaf.name} must be {k.__name__}{of}, got {v!r}')
    return tuple(leaf.item(e) for e in v) if k is tuple else k(v)


def build(cls, values: Mapping[str, Any], base=None):
    """A ``cls`` from dotted values; names not given keep ``base``'s (default: the defaults).
    Unknown names raise ValueError, values of the wrong type TypeError; each dataclass's own
    ``__post_init__`` checks the ranges."""
    known = {leaf.name: leaf for leaf in leaves(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f'unknown {cls.__name__} parameters: {unknown}')
    flat = flatten(base) if base is not None else {}
    flat.update({k: _coerce(known[k], v) for k, v in values.items()})
    return _nest(cls, flat, '')


def _nest(cls, flat: Mapping[str, Any], prefix: str):
    hints = typing.get_type_hints(cls)
    kw = {}
    for f in dataclasses.fields(cls):
        name = prefix + f.name
        if dataclasses.is_dataclass(hints[f.name]):
            kw[f.name] = _nest(hints[f.name], flat, name + '.')
        elif name in flat:
            v = flat[name]
            kw[f.name] = tuple(v) if isinstance(v, list) else v
    return cls(**kw)


def override(config, values: Mapping[str, Any]):
    """A copy of ``config`` with some dotted parameters changed."""
    return build(type(config), values, base=config)


def nested_to_dotted(doc: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """A YAML mapping written nested ({'observer': {'bandwidth': 5}}) in dotted form, as ROS
    reads a parameter file."""
    out = {}
    for k, v in doc.items():
        if isinstance(v, Mapping):
            out.update(nested_to_dotted(v, f'{prefix}{k}.'))
        else:
            out[prefix + k] = v
    return out
