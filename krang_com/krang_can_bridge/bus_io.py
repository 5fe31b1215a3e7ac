"""Receiving CAN frames cheaply: the kernel drops the frames a process does not read, and one
thread reads every bus.

Every frame a Python process receives costs it about 25 us here (a wake-up, the socket read,
python-can's decoding, a GIL hand-over); on a udp_multicast bus a process also hears every frame
it sends itself. `receive_only` asks the kernel to pass only the ids the process consumes: on
SocketCAN through python-can's `can_filters` (CAN_RAW_FILTER), on udp_multicast through a classic
BPF socket filter on the id in python-can's message encoding (any frame whose encoding it does not
recognise passes, so the filter only ever drops what it has read). `BusReader` reads all buses
from one thread with select() instead of one python-can Notifier thread per bus, whose wake-ups
compete for the GIL with the process's real work. `enlarge_receive_buffer` gives a bus's socket
a receive queue that outlasts a stall of the reader.

`SendThread` sends the frames no control loop waits for (the PowerCube polls and moves) from a
thread of its own, so that the executor, which sends the wheel currents from its command callback,
is never held up by dozens of sends, each a system call that hands the GIL to the other threads.

`Pump` is the reader of a node set composed in one process (krang_cli.composed): no thread, the
frames queued on in-process `virtual` buses are handed over when the composition calls `pump()`,
so what each node sees, and in which order, is the same in every run.
"""

from __future__ import annotations

import ctypes
import select
import socket
import struct
import threading
from typing import Callable, Iterable, Mapping

import can

BURST = 16  # frames read from one bus before the others get their turn
#: Receive queue asked for on every bus socket (the kernel grants twice the request, capped at
#: twice net.core.rmem_max). The default (rmem_default, 208 KB here) holds 256 udp_multicast
#: frames (the kernel charges a datagram about 830 bytes): 50 ms of the benchmark's 5,000 frames
#: a second, so a reader that stalled that long lost frames: DMU samples, and it could as well
#: have been a drive's EMCY.
RECEIVE_BUFFER_BYTES = 4 << 20
SO_ATTACH_FILTER = 26  # linux/socket.h (socket.SO_ATTACH_FILTER is not exported)
# classic BPF opcodes (linux/filter.h)
_LD_B_ABS, _LD_H_ABS = 0x30, 0x28
_JEQ_K, _JGE_K, _RET_K, _JA = 0x15, 0x35, 0x06, 0x05
_ACCEPT, _DROP = 0xFFFF, 0
# python-can's udp_multicast frame: a msgpack map of 11 keys, "timestamp" (a float64) first, then
# "arbitration_id"; a UDP socket's filter sees the 8-byte UDP header before it
_UDP = 8
_MAP11, _FIXSTR14, _UINT8, _UINT16 = 0x8B, 0xAE, 0xCC, 0xCD
_MAP_AT, _KEY_AT, _ID_AT = _UDP, _UDP + 20, _UDP + 35


def _ins(code: int, jt: int, jf: int, k: int) -> bytes:
    return struct.pack('HBBI', code, jt, jf, k)


def udp_multicast_filter(ids: Iterable[int]) -> bytes:
    """The BPF program (sock_filter array) passing the frames whose standard id is in `ids`, and
    every datagram whose layout it does not recognise."""
    ids = sorted({int(i) for i in ids})
    if not ids or len(ids) > 200 or not all(0 <= i <= 0x7FF for i in ids):
        raise ValueError(f'need 1 to 200 standard CAN ids, got {ids}')
    n = len(ids)
    # the id comparisons end at `match` (accept) or fall through to drop; `accept` follows them
    prog = [
        _ins(_LD_B_ABS, 0, 0, _MAP_AT),
        None,  # jeq MAP11 else accept
        _ins(_LD_B_ABS, 0, 0, _KEY_AT),
        None,  # jeq FIXSTR14 else accept
        _ins(_LD_B_ABS, 0, 0, _ID_AT),
        _ins(_JGE_K, 0, 0, 0x80),  # jt/jf patched: fixint (< 0x80) -> compare
        _ins(_JEQ_K, 0, 2, _UINT8),  # else -> uint16
        _ins(_LD_B_ABS, 0, 0, _ID_AT + 1),
        None,  # uint8: jump to compare
        _ins(_JEQ_K, 0, 0, _UINT16),  # jf patched -> accept (another encoding)
        _ins(_LD_H_ABS, 0, 0, _ID_AT + 1),
    ]
    compare = len(prog)
    accept = compare + n + 1
    prog[1] = _ins(_JEQ_K, 0, accept - 2, _MAP11)
    prog[3] = _ins(_JEQ_K, 0, accept - 4, _FIXSTR14)
    prog[5] = _ins(_JGE_K, 0, compare - 6, 0x80)
    prog[8] = _ins(_JA, 0, 0, compare - 9)
    prog[9] = _ins(_JEQ_K, 0, accept - 10, _UINT16)
    for j, i in enumerate(ids):
        prog.append(_ins(_JEQ_K, accept - (compare + j) - 1, 0, i))
    prog += [_ins(_RET_K, 0, 0, _DROP), _ins(_RET_K, 0, 0, _ACCEPT)]
    return b''.join(prog)


def receive_only(bus: can.BusABC, ids: Iterable[int]) -> None:
    """Let `bus` receive only standard frames with these ids (see the module docstring); on an
    interface with no kernel filter python-can filters in Python (correct, not cheaper)."""
    ids = sorted({int(i) for i in ids})
    if type(bus).__name__ == 'VirtualBus':
        # in-process queues, nothing to save; and with a Python filter recv(0) returns None at
        # the first frame it drops, before the queue is empty (Pump relies on an empty queue)
        return
    if type(bus).__name__ == 'UdpMulticastBus':
        program = ctypes.create_string_buffer(udp_multicast_filter(ids))
        fprog = struct.pack('HL', len(program.raw) // 8, ctypes.addressof(program))
        sock = socket.socket(fileno=bus.fileno())
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
        finally:
            sock.detach()
        return
    bus.set_filters([{'can_id': i, 'can_mask': 0x7FF, 'extended': False} for i in ids])


def enlarge_receive_buffer(bus: can.BusABC, size: int = RECEIVE_BUFFER_BYTES) -> int | None:
    """Ask for a receive queue of `size` bytes on `bus`'s socket (SocketCAN, udp_multicast);
    the bytes granted, or None for a bus without a socket (virtual)."""
    try:
        fd = bus.fileno()
    except NotImplementedError:
        return None
    if fd < 0:
        return None
    sock = socket.socket(fileno=fd)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        return sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    finally:
        sock.detach()


class BusReader:
    """Reads every bus of `buses` (name -> bus) on one thread and calls `on_frame(name, msg)` for
    each frame, in arrival order per bus; `on_error(name, exc)` when a bus fails (that bus is no
    longer read, as with a python-can Notifier). Buses without a file descriptor get a Notifier."""

    def __init__(
        self,
        buses: Mapping[str, can.BusABC],
        on_frame: Callable[[str, can.Message], None],
        on_error: Callable[[str, Exception], None],
        timeout_s: float = 0.1,
    ):
        self._on_frame, self._on_error, self._timeout = on_frame, on_error, timeout_s
        self._stop = threading.Event()
        self._by_fd: dict[int, tuple[str, can.BusABC]] = {}
        self._notifiers = []
        for name, bus in buses.items():
            try:
                fd = bus.fileno()
            except NotImplementedError:
                fd = -1
            if fd >= 0:
                self._by_fd[fd] = (name, bus)
            else:
                self._notifiers.append(can.Notifier(bus, [_Listener(self, name)], timeout_s))
        self._thread = threading.Thread(target=self._run, name='can-rx', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while self._by_fd and not self._stop.is_set():
            try:
                ready, _, _ = select.select(list(self._by_fd), [], [], self._timeout)
            except (OSError, ValueError):  # a bus closed under us (shutdown)
                return
            for fd in ready:
                name, bus = self._by_fd[fd]
                try:
                    # what is queued, up to BURST frames: one select per burst, and a busy bus
                    # (the wheel bus) that the thread cannot keep up with starves no other
                    for _ in range(BURST):
                        msg = bus.recv(0.0)
                        if msg is None:
                            break
                        self._on_frame(name, msg)
                except Exception as exc:  # noqa: BLE001 - reported, the other buses go on
                    if self._stop.is_set():
                        return
                    del self._by_fd[fd]
                    self._on_error(name, exc)

    def stop(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        for n in self._notifiers:
            n.stop(timeout_s)
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


class _Listener(can.Listener):
    def __init__(self, reader: BusReader, name: str):
        self.reader, self.name = reader, name

    def on_message_received(self, msg: can.Message) -> None:
        self.reader._on_frame(self.name, msg)

    def on_error(self, exc: Exception) -> None:
        self.reader._on_error(self.name, exc)


class SendThread:
    """Calls `send(frames)` for each batch `put` here, in order, on a thread of its own;
    `on_error(exc)` if a send raises (the thread goes on with the next batch).

    Measured on udp_multicast beside the device player (bench_ros_latency.py --robot), the 38
    PowerCube polls sent from the executor held it 1.8 ms at the median and 14 ms at the 99th
    percentile, 25 times a second: a wheel command arriving then waited as long.

    A batch `put` with a `key` replaces the batch of that key still waiting: a bus whose sends
    time out (2 ms a frame, a net unplugged) makes a poll round longer than its period, and the
    queue must neither grow nor send a joint target that a newer one replaced. The new batch goes
    last, not in the old one's place: a target for some of the same modules put in between would
    otherwise go out after it and leave those modules on the older target."""

    def __init__(
        self, send: Callable[[list], None], on_error: Callable[[Exception], None], name='can-tx'
    ):
        self._send, self._on_error = send, on_error
        self._waiting: list[list] = []  # [key, frames] in order
        self._cond = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def put(self, frames: list, key=None) -> None:
        if not frames:
            return
        with self._cond:
            if self._stopped:
                return
            if key is not None:
                self._waiting = [batch for batch in self._waiting if batch[0] != key]
            self._waiting.append([key, frames])
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._waiting or self._stopped)
                if self._stopped:
                    return
                _, frames = self._waiting.pop(0)
            try:
                self._send(frames)
            except Exception as exc:  # noqa: BLE001 - reported; the next batch may go through
                self._on_error(exc)

    def stop(self, timeout_s: float = 1.0) -> None:
        """Ends the thread; what is still waiting is dropped (no poll or move after a stop)."""
        with self._cond:
            self._stopped = True
            self._waiting.clear()
            self._cond.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


class Pump:
    """Hands the frames queued on in-process buses to their readers when `pump()` is called, in a
    fixed order (reader by reader in the order they were made, bus by bus by name, each bus's
    frames in order). `reader` takes BusReader's arguments and is used in its place."""

    def __init__(self):
        self._readers: list[_Pumped] = []

    def reader(self, buses, on_frame, on_error) -> '_Pumped':
        pumped = _Pumped(dict(sorted(buses.items())), on_frame, on_error)
        self._readers.append(pumped)
        return pumped

    def pump(self) -> int:
        """Deliver every frame queued now (and those the deliveries queue); the number."""
        delivered = 0
        while True:
            moved = sum(r.deliver() for r in self._readers)
            if not moved:
                return delivered
            delivered += moved


class _Pumped:
    def __init__(self, buses, on_frame, on_error):
        self.buses, self.on_frame, self.on_error = buses, on_frame, on_error
        self.stopped = False

    def deliver(self) -> int:
        n = 0
        for name, bus in list(self.buses.items()):
            if self.stopped:
                break
            try:
                while (msg := bus.recv(0.0)) is not None:
                    self.on_frame(name, msg)
                    n += 1
            except Exception as exc:  # noqa: BLE001 - as BusReader: that bus is no longer read
                del self.buses[name]
                self.on_error(name, exc)
        return n

    def stop(self, timeout_s: float = 1.0) -> None:
        self.stopped = True


class SendFailures:
    """Frames the buses refused: counted per bus, and each run of failures on a bus timed (from
    its first failure to the next frame that goes out), so that a bus refusing everything is told
    from one refusing a frame now and then. Called from every sending thread."""

    def __init__(self):
        self.counts: dict[str, int] = {}
        self._runs: dict[str, tuple[float, str]] = {}  # bus -> (first failure, last error)
        self._lock = threading.Lock()

    def failed(self, bus: str, error: str, now: float) -> float:
        """A send on `bus` raised `error` at `now`: how long its run of failures has lasted."""
        with self._lock:
            self.counts[bus] = self.counts.get(bus, 0) + 1
            since = self._runs.get(bus, (now, ''))[0]
            self._runs[bus] = (since, error)
        return now - since

    def sent(self, bus: str, now: float) -> float | None:
        """A frame went out on `bus`: the length of the run of failures it ended, else None."""
        if bus not in self._runs:
            return None
        with self._lock:
            run = self._runs.pop(bus, None)
        return None if run is None else now - run[0]

    def failing(self, now: float) -> dict[str, tuple[float, str]]:
        """Buses whose last send failed: {bus: (seconds since the run's first failure, last
        error)}."""
        with self._lock:
            return {bus: (now - since, error) for bus, (since, error) in self._runs.items()}
