"""The entry point of every node executable (console scripts, `ros2 run`, `krang bringup`).

It is deliberately light: Ctrl-C or SIGTERM while a node is still importing numpy, scipy or
pinocchio ends it quietly with exit code 0 instead of a KeyboardInterrupt traceback, and `--help`
prints what the node does and its parameters without starting it (no bus is opened, no node joins
the graph)."""

import faulthandler
import gc
import importlib
import os
import signal
import sys
import threading

# Before numpy is imported: our linear algebra is on 4x4 to 92x92 matrices, where OpenBLAS's
# thread pool gains nothing and, on a loaded machine, turned a 1 ms LQR redesign into 20-65 ms
# and stalled the control loop. A user's own setting wins.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

#: executable -> module with the node's `main()`, a docstring and `describe_parameters()`.
NODE_MODULES = {
    'sim_krang': 'krang_sim.node',
    'can_bridge': 'krang_can_bridge.node',
    'adrc_controller': 'krang_adrc_controller.node',
    'pose_server': 'krang_pose_server.node',
    'com_estimator': 'krang_com_estimator.node',
    'mcap_recorder': 'krang_bag.node',
    'state_publisher': 'krang_ros.state_publisher',
}


def _exit_now(signum, frame):
    """A signal while the node's module is imported: nothing is open yet, so leave at once. An
    exception raised here could be swallowed: a C extension's init turns it into an ImportError,
    which a library's optional import catches, and the node then started and ran on after Ctrl-C
    (1 start of 60 interrupted at random under load; test/test_node_exits.py)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


#: Seconds a node has for its clean stop after SIGINT or SIGTERM. Past it, faulthandler dumps
#: every thread's stack to stderr (the node's log) and ends the process with exit code 1: no
#: supervisor escalates to SIGKILL when the signal is `krang bringup`'s parent-death signal.
STOP_DEADLINE_S = 10.0


#: Set by a SIGINT or SIGTERM once the node's module is imported. `krang_ros.spin.run_node` ends
#: its loop when it is set, also where the SystemExit raised with it was lost.
STOP_REQUESTED = threading.Event()


def _exit_quietly(signum, frame):
    """Unwind, so that the node's close() runs (the bridge zeroes the currents), within
    STOP_DEADLINE_S (rclpy's own handlers are not installed, krang_ros.spin). Inside a
    finalizer (`__del__`) Python prints an exception and ignores it: the node then ran on after
    `krang bringup` was killed, with a traceback in its log. There the handler only sets
    STOP_REQUESTED, and run_node's loop ends at its next wake (within spin.STOP_CHECK_S). A
    later signal while that SystemExit unwinds does nothing: a Ctrl-C in a terminal reaches both
    the node and `krang bringup`, and one arriving while Python runs its exit hooks was printed
    as a traceback in the node's log (test_node_exits.py, CI)."""
    global _unwinding
    if _unwinding:
        return
    STOP_REQUESTED.set()
    faulthandler.dump_traceback_later(STOP_DEADLINE_S, exit=True)
    if not _in_finalizer(frame):
        _unwinding = True
        raise SystemExit(0)


_unwinding = False  # _exit_quietly raised its SystemExit


def interrupt(signum, frame):
    """SIGINT for a command that runs a session in its own process (`krang demo`). The first sets
    STOP_REQUESTED only, and the session loop (krang_ros.session_client) stops at its next step,
    between two calls into rclpy: a KeyboardInterrupt raised wherever the signal lands can leave
    a library mid-call (rclpy turned one inside a message's conversion into a RuntimeError
    traceback; a demo once hung in its close after one, and in a finalizer one is lost). A second
    Ctrl-C raises KeyboardInterrupt at once, outside a finalizer."""
    if STOP_REQUESTED.is_set() and not _in_finalizer(frame):
        raise KeyboardInterrupt
    STOP_REQUESTED.set()


def _in_finalizer(frame):
    """Whether `frame` runs inside a `__del__`, where an exception would be ignored."""
    while frame is not None:
        if frame.f_code.co_name == '__del__':
            return True
        frame = frame.f_back
    return False


def settle_garbage_collector():
    """Collect once, then move every object alive (the modules, the node, its configuration) out
    of reach of Python's cyclic garbage collector. With numpy, scipy and pinocchio loaded a full
    pass walks about 135,000 objects: in bench_ros_latency.py the controller's and the bridge's
    took 40-190 ms while they started, during which a process answers nothing. After the freeze
    a full pass walks only what the node built since. In the benchmark's 20 s of balancing no full
    pass ran either way: this guards the long run on the robot, not a figure. Called once a node
    or a composition is built, before it runs; stdlib only, so the benchmark's device player
    (no rclpy) uses it too."""
    gc.collect()
    gc.freeze()


def run(executable, argv=None):
    """Run the node `executable`. A signal while its module imports ends it at once; a later one
    unwinds it, with STOP_DEADLINE_S for its clean stop. A crash
    writes the threads' stacks to stderr (faulthandler)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    # a crash in a C extension (a segfault, an abort) leaves every thread's Python stack in the
    # node's log instead of only its exit code
    faulthandler.enable()
    signal.signal(signal.SIGINT, _exit_now)
    signal.signal(signal.SIGTERM, _exit_now)
    ros_args = argv[argv.index('--ros-args') :] if '--ros-args' in argv else []
    own = argv[: len(argv) - len(ros_args)]
    module = importlib.import_module(NODE_MODULES[executable])
    # from here the node may hold a bus or a drive: a signal unwinds, so that close() runs
    signal.signal(signal.SIGINT, _exit_quietly)
    signal.signal(signal.SIGTERM, _exit_quietly)
    if own and own[0] in ('-h', '--help'):
        print(help_text(executable, module))
        return 0
    if own:
        print(
            f'{executable}: unknown arguments {own}; parameters go after --ros-args '
            f'(-p name:=value, --params-file FILE). See {executable} --help.',
            file=sys.stderr,
        )
        return 2
    return module.main([executable] + ros_args)


def help_text(executable, module):
    """The node's docstring, then its parameters (the module's `describe_parameters()`)."""
    lines = [
        f'usage: {executable} [--help] [--ros-args -p NAME:=VALUE ... --params-file FILE]',
        '',
        (module.__doc__ or '').strip(),
    ]
    described = module.describe_parameters()
    lines += ['', 'parameters:'] + ([f'  {line}' for line in described] or ['  (none)'])
    return '\n'.join(lines)


def sim_krang():
    return run('sim_krang')


def can_bridge():
    return run('can_bridge')


def adrc_controller():
    return run('adrc_controller')


def pose_server():
    return run('pose_server')


def com_estimator():
    return run('com_estimator')


def mcap_recorder():
    return run('mcap_recorder')


def state_publisher():
    return run('state_publisher')


if __name__ == '__main__':
    sys.exit(run(sys.argv[1], sys.argv[2:]))
