"""SCHED_FIFO for the control path (krang_ros/realtime.py): every thread of the process, those
started before and after; the robot's parameter files run can_bridge and adrc_controller under it
and the simulated set on the default scheduler; a refused priority is a warning and the default
scheduler; a priority out of range is one line and exit code 2."""

import json
import os
import resource
import subprocess
import sys
import textwrap
import time

import pytest

from krang_cli.node_set import file_parameter, params_files
from krang_cli.processes import NodeSet
from krang_core import params
from krang_ros.realtime import SchedulingParams

CONTROL_PATH = ('can_bridge', 'adrc_controller')


def fifo_permitted(priority):
    """Whether this process may use SCHED_FIFO at `priority` (root, or an rtprio limit)."""
    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= priority


def scheduling(pid):
    """{thread id: (policy, priority)} of every thread of process `pid`."""
    out = {}
    for tid in os.listdir(f'/proc/{pid}/task'):
        try:
            out[int(tid)] = (
                os.sched_getscheduler(int(tid)),
                os.sched_getparam(int(tid)).sched_priority,
            )
        except ProcessLookupError:
            pass
    return out


def run_python(code, timeout=60):
    return subprocess.run(
        [sys.executable, '-c', textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.mark.parametrize('value', [0, 1, 40, 99])
def test_thread_priority_takes_0_to_99(value):
    assert params.build(SchedulingParams, {'thread_priority': value}).thread_priority == value


@pytest.mark.parametrize('value', [-1, 100])
def test_thread_priority_out_of_range_is_refused_by_name(value):
    with pytest.raises(ValueError, match='thread_priority'):
        params.build(SchedulingParams, {'thread_priority': value})


def test_the_robot_runs_the_control_path_under_fifo_and_the_simulation_does_not():
    robot = {n: file_parameter(n, 'thread_priority', sim=False, default=0) for n in CONTROL_PATH}
    sim = {n: file_parameter(n, 'thread_priority', sim=True, default=0) for n in CONTROL_PATH}
    assert len(set(robot.values())) == 1 and robot['can_bridge'] > 0, robot
    assert set(sim.values()) == {0}, sim


def test_every_thread_started_before_and_after_runs_under_fifo():
    if not fifo_permitted(7):
        pytest.skip('SCHED_FIFO not permitted here (neither root nor an rtprio limit of 7)')
    proc = run_python(
        """
        import json, os, threading
        from krang_ros.realtime import set_fifo_priority
        done = threading.Event()
        threading.Thread(target=done.wait).start()
        set_fifo_priority(7)
        threading.Thread(target=done.wait).start()
        tasks = os.listdir('/proc/self/task')
        print(json.dumps([[os.sched_getscheduler(int(t)), os.sched_getparam(int(t)).sched_priority]
                          for t in tasks]))
        done.set()
        """
    )
    assert proc.returncode == 0, proc.stderr
    threads = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(threads) == 3
    assert all(t == [os.SCHED_FIFO, 7] for t in threads), threads
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the test's own process is untouched


@pytest.mark.ros
def test_a_refused_priority_is_one_warning_and_the_default_scheduler():
    """Without CAP_SYS_NICE (root drops to nobody) and with no rtprio limit the node logs why and
    goes on at the default scheduler."""
    proc = run_python(
        """
        import os, resource, sys
        import rclpy
        from rclpy.node import Node
        from rclpy.parameter import Parameter
        from krang_ros.realtime import declare_thread_priority
        rclpy.init()
        node = Node('t', parameter_overrides=[Parameter('thread_priority', value=7)])
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
        if os.geteuid() == 0:
            os.setuid(65534)
        print('in effect', declare_thread_priority(node), os.sched_getscheduler(0), flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
        """
    )
    assert proc.returncode == 0, proc.stderr
    assert f'in effect 0 {os.SCHED_OTHER}' in proc.stdout, proc.stdout
    warnings = [line for line in proc.stderr.splitlines() if 'thread_priority 7 refused' in line]
    assert len(warnings) == 1 and 'default scheduler' in warnings[0], proc.stderr


@pytest.mark.ros
def test_a_priority_out_of_range_is_one_line_and_exit_2(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            '-m',
            'krang_ros.entry',
            'adrc_controller',
            '--ros-args',
            '-p',
            'thread_priority:=100',
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    out = (proc.stdout + proc.stderr).strip()
    assert proc.returncode == 2 and 'Traceback' not in out, out
    errors = [line for line in out.splitlines() if line.startswith('error:')]
    assert len(errors) == 1 and 'thread_priority' in errors[0], out


@pytest.mark.ros
@pytest.mark.timeout(120)
def test_the_robot_configuration_runs_every_thread_of_the_control_path_under_fifo(tmp_path):
    """can_bridge (on a multicast map: the robot's SocketCAN buses are not here) and
    adrc_controller started with the robot's parameter files, as `krang bringup` starts them."""
    priority = file_parameter('can_bridge', 'thread_priority', sim=False)
    if not fifo_permitted(priority):
        pytest.skip(
            f'SCHED_FIFO not permitted here (neither root nor an rtprio limit of {priority})'
        )
    from krang_sim.session_config import session_devices_file

    nodes = NodeSet(params_files(sim=False), log_dir=tmp_path / 'logs')
    procs = {
        'can_bridge': nodes.start('can_bridge', {'devices_file': session_devices_file(tmp_path)}),
        'adrc_controller': nodes.start('adrc_controller'),
    }
    try:
        line = f'every thread under SCHED_FIFO priority {priority}'
        deadline = time.monotonic() + 60.0
        logs = {n: tmp_path / 'logs' / f'{n}.log' for n in procs}
        while not all(logs[n].exists() and line in logs[n].read_text() for n in procs):
            assert time.monotonic() < deadline, {n: logs[n].read_text()[-2000:] for n in procs}
            assert not nodes.dead(), nodes.dead()
            time.sleep(0.2)
        time.sleep(1.0)  # the threads the nodes start once built (receive, heartbeat, sender)
        for name, proc in procs.items():
            threads = scheduling(proc.pid)
            assert len(threads) > 3, (name, threads)
            assert set(threads.values()) == {(os.SCHED_FIFO, priority)}, (name, threads)
    finally:
        nodes.stop()


@pytest.mark.parametrize('executable', CONTROL_PATH)
def test_help_lists_the_thread_priority(executable):
    proc = subprocess.run(
        [sys.executable, '-m', 'krang_ros.entry', executable, '--help'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert 'thread_priority (int, 0): SCHED_FIFO priority' in proc.stdout, proc.stdout
