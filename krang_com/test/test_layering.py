"""The layers, read from the source (AST, nothing imported): a ROS-free core under thin ROS shells.

The shells are the modules whose job is ROS: krang_ros (rclpy nodes' plumbing, message packing,
the session client, the launch description), each part's node module (`<part>/node.py`, the rclpy
node around its core) and the command-line modules that start, compose or talk to nodes
(SHELL_CLI). Every other module of the package is core: it must not import rclpy, a ROS message,
service or action package, or krang_ros, so it runs and is tested without ROS and an offline tool
never pulls in a message package. Shells may import the core, never the other way round.

Also: no import cycle between the package's modules (lazy imports inside functions included).
"""

import ast
import functools
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.name for p in REPO.iterdir() if (p / '__init__.py').exists())

#: The command-line modules that start, compose or talk to ROS nodes.
SHELL_CLI = frozenset(
    {
        'krang_cli.bringup',  # starts the node set as processes
        'krang_cli.composed',  # composes the nodes in one process (rclpy executor)
        'krang_cli.demo',  # runs a session through the session client
        'krang_cli.processes',  # starts node processes at the robot's thread priority
        'krang_cli.view',  # the live Foxglove view, an rclpy node
    }
)
#: Top-level import names that are ROS (besides any *_msgs, *_srvs, *_interfaces package).
ROS_MODULES = frozenset(
    {'rclpy', 'rcl_interfaces', 'builtin_interfaces', 'launch', 'launch_ros', 'krang_ros'}
)


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


@functools.cache
def modules() -> dict[str, Path]:
    return {
        module_name(path): path for package in PACKAGES for path in (REPO / package).rglob('*.py')
    }


def is_shell(name: str) -> bool:
    return name.split('.')[0] == 'krang_ros' or name.endswith('.node') or name in SHELL_CLI


def is_ros(imported: str) -> bool:
    top = imported.split('.')[0]
    return top in ROS_MODULES or top.endswith(('_msgs', '_srvs', '_interfaces'))


@functools.cache
def imports_of(name: str, path: Path) -> frozenset[str]:
    """Every module name `name` imports, relative imports resolved; `from a import b` counts as
    `a.b` too (b may be a module)."""
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split('.')
                base = base[: len(base) - node.level + 1]
                module = '.'.join(base + ([node.module] if node.module else []))
            else:
                module = node.module
            found.add(module)
            found.update(f'{module}.{alias.name}' for alias in node.names)
    return frozenset(found)


@functools.cache
def own_graph() -> dict[str, set[str]]:
    """module -> the package's modules it imports."""
    mods = modules()
    return {
        name: {m for m in imports_of(name, path) if m in mods and m != name}
        for name, path in mods.items()
    }


def test_the_shells_are_the_expected_modules():
    mods = modules()
    assert SHELL_CLI <= set(mods), 'SHELL_CLI names a module that does not exist'
    nodes = {name for name in mods if name.endswith('.node')}
    assert 'krang_can_bridge.node' in nodes and 'krang_adrc_controller.node' in nodes


@pytest.mark.parametrize('name', sorted(n for n in modules() if not is_shell(n)))
def test_core_module_imports_no_ros(name):
    ros = sorted(m for m in imports_of(name, modules()[name]) if is_ros(m))
    assert not ros, f'{name} is core but imports {ros}'


@pytest.mark.parametrize('name', sorted(n for n in modules() if not is_shell(n)))
def test_core_module_imports_no_shell(name):
    shells = sorted(m for m in own_graph()[name] if is_shell(m))
    assert not shells, f'{name} is core but imports the ROS shells {shells}'


def test_no_import_cycles():
    graph = own_graph()
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(graph)))
    state, stack, cycles = {}, [], []

    def visit(name):
        state[name] = 'open'
        stack.append(name)
        for other in sorted(graph[name]):
            if state.get(other) == 'open':
                cycles.append(stack[stack.index(other) :] + [other])
            elif other not in state:
                visit(other)
        stack.pop()
        state[name] = 'done'

    for name in sorted(graph):
        if name not in state:
            visit(name)
    assert not cycles, 'import cycles:\n' + '\n'.join(' -> '.join(c) for c in cycles)
