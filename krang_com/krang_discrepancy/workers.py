"""Worker interpreters for work that is independent and long enough to pay for one: fresh Python
processes started with the caller's module path and fed pickled calls over pipes. Not forked
(the caller has threads) nor started by ``multiprocessing`` (whose spawned workers run the
caller's main script again, unguarded scripts included)."""

from __future__ import annotations

import importlib
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
from concurrent.futures import Future


class Workers:
    """`n` worker interpreters (``serve``), one feeding thread each. ``submit(fn, arg)`` calls
    the module-level function `fn` on `arg` in a worker and returns a ``Future``; a worker that
    dies fails its job and every later one it takes (the caller decides what to do then)."""

    def __init__(self, n: int):
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        cmd = [sys.executable, '-c', f'from {__name__} import serve; serve()']
        self._procs = [
            subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
            for _ in range(n)
        ]
        self._queue = queue.SimpleQueue()
        for p in self._procs:
            threading.Thread(target=self._feed, args=(p,), daemon=True).start()

    def submit(self, fn, arg) -> Future:
        fut = Future()
        self._queue.put((fut, (fn.__module__, fn.__qualname__, arg)))
        return fut

    def _feed(self, proc):
        while True:
            item = self._queue.get()
            if item is None:
                return
            fut, job = item
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                pickle.dump(job, proc.stdin)
                proc.stdin.flush()
                ok, value = pickle.load(proc.stdout)
            except Exception as exc:  # the worker is gone
                fut.set_exception(exc)
                continue
            if ok:
                fut.set_result(value)
            else:
                fut.set_exception(RuntimeError(value))

    def close(self):
        """Stop the workers now (jobs not finished fail)."""
        for _ in self._procs:
            self._queue.put(None)
        for p in self._procs:
            p.kill()
            p.wait()
            for f in (p.stdin, p.stdout):
                f.close()


def serve():
    """A worker: pickled (module, function, argument) in on stdin, (ok, result or error) out on
    stdout, until stdin closes."""
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # whatever the work prints must not enter the pipe
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the caller's: it stops the workers
    while True:
        try:
            module, name, arg = pickle.load(inp)
        except EOFError:
            return
        try:
            res = (True, getattr(importlib.import_module(module), name)(arg))
        except Exception as exc:
            res = (False, f'{type(exc).__name__}: {exc}')
        pickle.dump(res, out)
        out.flush()
