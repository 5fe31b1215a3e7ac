"""Message definitions and type hashes for installed ROS 2 interfaces, as rosbag2 stores them.

rosbag2 (Jazzy) embeds a `ros2msg` schema per topic type: the root `.msg` text, then for every
dependency a line of 80 '=' and `MSG: pkg/Type` followed by that type's text. Foxglove, mcap_ros2
and rosbags all rebuild their decoders from that text, so it must be complete and exact. We read
the same `share/<pkg>/msg/*.msg` files that rosbag2 reads, mirroring its dependency walk
(`rosbag2_cpp/message_definitions/local_message_definition_source.cpp`).

The PyPI wheels install `share/` next to `lib/` without setting AMENT_PREFIX_PATH, so the share
directory is found through ament_index when it is configured, else next to the installed package.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import os
import re
import sys
from pathlib import Path

SCHEMA_ENCODING = 'ros2msg'
SEPARATOR = '=' * 80

# Same primitive set as rosbag2, plus wstring which rosbag2 forgets.
_PRIMITIVES = frozenset(
    {
        'bool',
        'byte',
        'char',
        'float32',
        'float64',
        'int8',
        'uint8',
        'int16',
        'uint16',
        'int32',
        'uint32',
        'int64',
        'uint64',
        'string',
        'wstring',
    }
)
# First token of a field line: "pkg/Type[] name", "Type[<=3] name", "string<=10 name", "int32 X=1".
_FIELD_TYPE = re.compile(r'^\s*([A-Za-z][A-Za-z0-9_/]*)(?:<=\d+)?(?:\[[^\]]*\])?\s+\S')
_NAME = r'[A-Za-z][A-Za-z0-9_]*'


class SchemaNotFoundError(LookupError):
    """No installed interface file for a type (package not installed, or not a .msg type)."""


def split_type_name(type_name: str) -> tuple[str, str, str]:
    """('pkg', 'msg', 'Type') from 'pkg/msg/Type' or 'pkg/Type' (the .msg spelling)."""
    match = re.fullmatch(rf'({_NAME})/({_NAME})/({_NAME})', type_name) or re.fullmatch(
        rf'({_NAME})/()({_NAME})', type_name
    )
    if not match:
        raise ValueError(f'not a ROS 2 type name: {type_name!r} (expected pkg/msg/Type)')
    package, interface, name = match.groups()
    return package, interface or 'msg', name


def normalize_type_name(type_name: str) -> str:
    """'pkg/msg/Type', the form topics, MCAP schema names and type hashes use."""
    return '/'.join(split_type_name(type_name))


def type_name_of(msg_or_class) -> str:
    """'pkg/msg/Type' of an rclpy message instance or class (module 'pkg.msg._type')."""
    cls = msg_or_class if isinstance(msg_or_class, type) else type(msg_or_class)
    parts = cls.__module__.split('.')
    if len(parts) < 2:
        raise ValueError(f'{cls!r} is not a generated ROS 2 interface class')
    return f'{parts[0]}/{parts[1]}/{cls.__name__}'


@functools.lru_cache(maxsize=None)
def package_share_directory(package: str) -> Path:
    """share/<package> of an installed interface package: ament index first, then beside the
    wheel."""
    candidates: list[Path] = []
    if os.environ.get('AMENT_PREFIX_PATH'):
        try:
            from ament_index_python.packages import get_package_share_directory

            candidates.append(Path(get_package_share_directory(package)))
        except (LookupError, OSError, ImportError, ValueError):
            pass
    spec = importlib.util.find_spec(package)
    if spec is not None and spec.origin:
        # <prefix>/lib/pythonX.Y/site-packages/<pkg>/__init__.py -> <prefix>/share/<pkg>
        candidates += [
            parent / 'share' / package for parent in Path(spec.origin).resolve().parents
        ]
    candidates += [Path(prefix) / 'share' / package for prefix in (sys.prefix, sys.base_prefix)]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    raise SchemaNotFoundError(
        f'share directory of ROS package {package!r} not found (is it '
        'installed? '
        f'AMENT_PREFIX_PATH={os.environ.get("AMENT_PREFIX_PATH")!r})'
    )


def interface_file(type_name: str, suffix: str) -> Path:
    """The installed share/<pkg>/<msg|srv>/<Type><suffix> file of a type."""
    package, interface, name = split_type_name(type_name)
    path = package_share_directory(package) / interface / f'{name}{suffix}'
    if not path.is_file():
        raise SchemaNotFoundError(f'no {suffix} file for {type_name}: {path} does not exist')
    return path


def _dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a .msg text, as written, sorted like rosbag2's std::set."""
    found = set()
    for line in text.splitlines():
        line = line.split('#', 1)[0]
        match = _FIELD_TYPE.match(line)
        if not match or match.group(1) in _PRIMITIVES:
            continue
        field_type = match.group(1)
        found.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return sorted(found)


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """Full ros2msg schema text of an installed message type (root first, deps depth-first)."""
    seen: set[str] = set()

    def text_with_dependencies(name: str, depth: int) -> str:
        if depth <= 0:
            raise RecursionError(f'message definition of {type_name} nests too deeply')
        text = interface_file(name, '.msg').read_text(encoding='utf-8')
        package = split_type_name(name)[0]
        for dependency in _dependencies(text, package):
            key = normalize_type_name(dependency)
            if key not in seen:
                seen.add(key)
                text += f'\n{SEPARATOR}\nMSG: {dependency}\n' + text_with_dependencies(
                    dependency, depth - 1
                )
        return text

    return text_with_dependencies(normalize_type_name(type_name), 50)


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """'RIHS01_<sha256>' of a type, from the type description JSON that rosidl installs."""
    full_name = normalize_type_name(type_name)
    description = json.loads(interface_file(full_name, '.json').read_text(encoding='utf-8'))
    for entry in description.get('type_hashes', []):
        if entry.get('type_name') == full_name:
            return entry['hash_string']
    raise SchemaNotFoundError(f'no type hash for {full_name} in its type description JSON')
