"""Start the node set as child processes and stop it cleanly (our stand-in for ros2 launch)."""

import ctypes
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time

from krang_ros.realtime import set_fifo_priority

log = logging.getLogger('krang.bringup')


_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_libc = ctypes.CDLL(None, use_errno=True)  # loaded here: the child runs no more than a call


def child_setup(rt_priority=0):
    """A preexec_fn for a node process:
    - it gets SIGINT, its clean stop, when the thread that started it dies, even by SIGKILL,
      so no node outlives the `krang` command that started it (call `NodeSet.start` from a
      thread that lives as long as the nodes should: the main one);
    - with `rt_priority` > 0 it runs, and every thread it starts, under SCHED_FIFO at that
      priority (needs CAP_SYS_NICE or an rtprio limit; without it the child keeps the default
      policy, which `is_real_time` then shows): for processes that are not our nodes (the
      benchmarks' device player and reference chain)."""
    parent = os.getpid()

    def apply():
        _libc.prctl(_PR_SET_PDEATHSIG, signal.SIGINT)
        if os.getppid() != parent:  # the parent died before the prctl
            os.kill(os.getpid(), signal.SIGINT)
        if rt_priority > 0:
            try:
                set_fifo_priority(rt_priority)
            except OSError:
                pass

    return apply


class WorkingDir:
    """A run's temporary directory (node logs, records): removed when the run ends normally,
    kept and named on stderr when it fails or `keep` is called, so a failure's logs stay."""

    def __init__(self, prefix):
        self.path = tempfile.mkdtemp(prefix=prefix)
        self.kept = False

    def keep(self, why):
        self.kept = True
        print(f'{why}: logs and records kept in {self.path}', file=sys.stderr)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self.keep(f'{exc_type.__name__}')
        elif not self.kept:
            shutil.rmtree(self.path, ignore_errors=True)
        return False


def is_real_time(pid):
    """Whether process `pid` runs under SCHED_FIFO."""
    return os.sched_getscheduler(pid) == os.SCHED_FIFO


class NodeSet:
    """A group of node processes that live and die together."""

    def __init__(self, params_files, log_dir=None, env=None):
        self.params_files = [str(p) for p in params_files]
        self.log_dir = log_dir
        self.env = dict(os.environ if env is None else env)
        self.procs = {}

    def start(self, name, extra_params=None):
        """Start node `name` with `extra_params`, in a session of its own (a Ctrl-C at the
        terminal reaches `stop`, which stops the nodes in order), stopped with this process
        (`child_setup`). A node of the control path sets its own scheduling (its
        thread_priority parameter, krang_ros/realtime.py)."""
        cmd = [sys.executable, '-m', 'krang_ros.entry', name, '--ros-args']
        for f in self.params_files:
            cmd += ['--params-file', f]
        for key, value in (extra_params or {}).items():
            cmd += ['-p', f'{key}:={value}']
        out = None
        if self.log_dir:
            os.makedirs(self.log_dir, exist_ok=True)
            out = open(os.path.join(self.log_dir, f'{name}.log'), 'w')
        log.info('starting %s', name)
        self.procs[name] = (
            subprocess.Popen(
                cmd,
                stdout=out,
                stderr=subprocess.STDOUT if out else None,
                env=self.env,
                start_new_session=True,
                preexec_fn=child_setup(),
            ),
            out,
        )
        return self.procs[name][0]

    def dead(self):
        """Names of nodes that exited, with their return codes."""
        return {n: p.returncode for n, (p, _) in self.procs.items() if p.poll() is not None}

    def stop(self, order=None, timeout=10.0):
        """SIGINT in order (recorder last, so it sees everything), then SIGTERM, then SIGKILL."""
        names = list(order or self.procs)
        names += [n for n in self.procs if n not in names]
        for name in (n for n in names if n in self.procs):
            proc, out = self.procs[name]
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(timeout)
                except subprocess.TimeoutExpired:
                    log.warning('%s ignored SIGINT, sending SIGTERM', name)
                    proc.terminate()
                    try:
                        proc.wait(timeout)
                    except subprocess.TimeoutExpired:
                        log.error('%s ignored SIGTERM, killing it', name)
                        proc.kill()
                        proc.wait()
            if out:
                out.close()
            log.info('%s exited with %s', name, proc.returncode)
        self.procs.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def wait_forever(node_set, poll=0.5):
    """Run until Ctrl-C or until a node dies; returns an exit code."""
    stop = {'flag': False}

    def on_signal(signum, frame):
        stop['flag'] = True

    signal.signal(signal.SIGTERM, on_signal)
    try:
        while not stop['flag']:
            dead = node_set.dead()
            if dead:
                log.error('node(s) exited: %s; stopping the rest', dead)
                return 1
            time.sleep(poll)
    except KeyboardInterrupt:
        pass
    return 0
