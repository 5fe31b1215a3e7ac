"""Receiving cheaply and sending off the executor (krang_can_bridge/bus_io.py), and the struct
codecs compiled from the DBC."""

import random
import threading
import time
from pathlib import Path

import can
import pytest

from krang_can_bridge.bridge import BridgeCore
from krang_can_bridge.bus_io import (
    RECEIVE_BUFFER_BYTES,
    BusReader,
    Pump,
    SendThread,
    enlarge_receive_buffer,
    receive_only,
)
from krang_can_bridge.config import load_devices
from krang_can_bridge.protocols import FrameLayout, ValueOutOfRange, load_dbc
from krang_can_bridge.protocols import powercube as pc
from krang_model.config import config_path
from krang_sim.devices import KrangCanDevices
from krang_sim.session_config import private_port


def _bus(port):
    return can.Bus(interface='udp_multicast', channel='239.74.163.201', port=port)


def _collect(buses, seconds=0.3):
    got = []
    reader = BusReader(buses, lambda name, m: got.append((name, m.arbitration_id)), print)
    time.sleep(seconds)
    reader.stop()
    return got


def test_udp_multicast_kernel_filter_passes_only_the_ids_asked_for():
    port = private_port()
    rx, tx = _bus(port), _bus(port)
    try:
        keep = {0x05, 0x50, 0xA4, 0x2E3, 0x701}  # msgpack: fixint, uint8, uint16 encodings
        receive_only(rx, keep)
        sent = [0x05, 0x06, 0x50, 0x7F, 0x80, 0xA4, 0xA5, 0xFF, 0x100, 0x2E3, 0x2E4, 0x701, 0x7FF]
        for i in sent:
            tx.send(can.Message(arbitration_id=i, data=b'\x01', is_extended_id=False))
        # an encoding the filter does not read (an extended id) passes: it only drops what it read
        tx.send(can.Message(arbitration_id=0x12345, data=b'\x01', is_extended_id=True))
        got = [aid for _, aid in _collect({'rx': rx})]
        assert got == sorted(keep) + [0x12345]
    finally:
        rx.shutdown()
        tx.shutdown()


RMEM = ('rmem_default', 'rmem_max')


def test_an_enlarged_receive_queue_keeps_the_frames_of_a_stalled_reader():
    """1,000 frames (0.2 s of the benchmark's buses) sent while nobody reads: the default queue
    keeps only a few hundred, the enlarged one all of them, in order."""
    port = private_port()
    n = 1000

    def kept(enlarge):
        rx, tx = _bus(port), _bus(port)
        try:
            receive_only(rx, {0x181})  # the sender's own echo is not counted
            if enlarge:
                assert enlarge_receive_buffer(rx) >= RECEIVE_BUFFER_BYTES  # rmem_max permitting
            for k in range(n):
                tx.send(can.Message(arbitration_id=0x181, data=k.to_bytes(2, 'little')))
            time.sleep(0.2)
            got = []
            while (m := rx.recv(0)) is not None:
                got.append(int.from_bytes(m.data, 'little'))
            return got
        finally:
            rx.shutdown()
            tx.shutdown()

    rmem = {k: int(Path(f'/proc/sys/net/core/{k}').read_text()) for k in RMEM}
    if rmem['rmem_default'] <= 212992:  # the kernel's default: a few hundred frames
        assert len(kept(False)) < n
    if 2 * rmem['rmem_max'] < 1 << 20:
        pytest.skip(f'net.core.rmem_max is {rmem["rmem_max"]} bytes: no queue for {n} frames')
    assert kept(True) == list(range(n))
    virtual = can.Bus(interface='virtual', channel='enlarge-test')
    try:
        assert enlarge_receive_buffer(virtual) is None  # no socket, nothing to enlarge
    finally:
        virtual.shutdown()


def test_reader_serves_every_bus_while_one_is_flooded():
    port = private_port()
    a, b = _bus(port), can.Bus(interface='udp_multicast', channel='239.74.163.202', port=port + 1)
    tx_a, tx_b = (
        _bus(port),
        can.Bus(interface='udp_multicast', channel='239.74.163.202', port=port + 1),
    )
    try:
        for k in range(200):  # within the default socket buffer
            tx_a.send(
                can.Message(arbitration_id=0x10, data=bytes([k % 256]), is_extended_id=False)
            )
        tx_b.send(can.Message(arbitration_id=0x20, data=b'\x00', is_extended_id=False))
        got = _collect({'a': a, 'b': b})
        names = [n for n, _ in got]
        assert names.count('a') == 200 and names.count('b') == 1
        # a burst of at most 16 frames per bus before the other bus gets its turn
        assert names.index('b') <= 16
    finally:
        for bus in (a, b, tx_a, tx_b):
            bus.shutdown()


def test_reader_serves_the_buses_in_the_order_given():
    """When several buses have frames waiting, the first bus given is read first: can_bridge gives
    the DMU's bus first, so a DMU frame never waits behind the PowerCube nets' frames."""
    port = private_port()
    for order in (('a', 'b'), ('b', 'a')):
        rx = {'a': _bus(port), 'b': _bus(port + 1)}
        tx = {'a': _bus(port), 'b': _bus(port + 1)}
        try:
            for name in ('b', 'a'):  # sent in the other order; queued before the reader starts
                for k in range(3):
                    tx[name].send(can.Message(arbitration_id=0x10 + k, is_extended_id=False))
            time.sleep(0.05)
            got = [n for n, _ in _collect({n: rx[n] for n in order})]
            assert got == [order[0]] * 3 + [order[1]] * 3
        finally:
            for bus in (*rx.values(), *tx.values()):
                bus.shutdown()


def test_bridge_reads_every_device_frame_and_no_host_frame():
    config = load_devices(config_path('can_devices.yaml'))
    core = BridgeCore(config)
    devices = KrangCanDevices(config, auto_enable_wheels=True)
    wheels = {j: 0.1 for j in devices.wheels}
    device_frames = devices.wheel_feedback_frames(wheels, wheels) + devices.imu_frames_from_pitch(
        -1.0, 0.0
    )
    device_frames += [r for f in core.poll_frames() for r in devices.on_frame(f.bus, f.msg)]
    for f in device_frames:
        assert f.msg.arbitration_id in core.received_ids(f.bus), hex(f.msg.arbitration_id)
    host_frames = core.poll_frames() + core.wheel_current_frames(0.0, 0.0)
    for f in host_frames:
        assert f.msg.arbitration_id not in core.received_ids(f.bus)
        assert f.msg.arbitration_id in devices.host_ids(f.bus)
    assert all(
        pc.ACK_BASE < aid <= pc.ACK_BASE + pc.MODULE_ID_MASK for aid in core.received_ids('can0')
    )


def _virtual(channel):
    return can.Bus(interface='virtual', channel=channel)


def test_pump_hands_over_everything_queued_in_a_fixed_order():
    """Two readers (a host and a device, as the bridge and sim_krang composed): one pump() hands
    over every frame, the replies the handlers send included, reader by reader, bus by bus by
    name, each bus in order; nothing arrives without a pump()."""
    tag = f'pump-{random.random()}'
    host = {name: _virtual(f'{tag}-{name}') for name in ('b', 'a')}
    device = {name: _virtual(f'{tag}-{name}') for name in ('a', 'b')}
    got = []

    def on_device(name, msg):
        got.append(('device', name, msg.arbitration_id))
        host_reply = can.Message(arbitration_id=msg.arbitration_id + 0x80, is_extended_id=False)
        device[name].send(host_reply)

    pump = Pump()
    pump.reader(host, lambda name, m: got.append(('host', name, m.arbitration_id)), print)
    pump.reader(device, on_device, print)
    for i in (1, 2):
        host['b'].send(can.Message(arbitration_id=0x10 + i, is_extended_id=False))
        host['a'].send(can.Message(arbitration_id=0x20 + i, is_extended_id=False))
    receive_only(device['a'], {0x21})  # no effect on an in-process bus: 0x22 still arrives
    time.sleep(0.05)
    assert got == []
    assert pump.pump() == 8
    assert got == [
        ('device', 'a', 0x21),
        ('device', 'a', 0x22),
        ('device', 'b', 0x11),
        ('device', 'b', 0x12),
        ('host', 'a', 0xA1),
        ('host', 'a', 0xA2),
        ('host', 'b', 0x91),
        ('host', 'b', 0x92),
    ]
    assert pump.pump() == 0
    for bus in (*host.values(), *device.values()):
        bus.shutdown()


def test_send_thread_keeps_order_and_never_holds_up_the_caller():
    """put() returns while a send blocks; batches go out in order; a batch with a key replaces
    the waiting one of that key (and goes last), so a stuck bus never grows the queue; a send that
    raises is reported and the next batch still goes; after stop() nothing waiting goes out."""
    sent, errors = [], []
    release = threading.Event()

    def send(frames):
        if frames == ['block']:
            release.wait(5.0)
        if frames == ['boom']:
            raise can.CanOperationError('bus off')
        sent.append(frames)

    sender = SendThread(send, errors.append)
    sender.put(['block'])
    time.sleep(0.05)  # the thread is in that send now
    start = time.monotonic()
    sender.put(['move a 1'], key='a')
    for k in range(50):
        sender.put([f'poll {k}'], key='poll')  # a poll round every period while the bus hangs
    sender.put(['move b'], key='b')
    sender.put(['move a 2'], key='a')
    sender.put(['boom'])
    sender.put(['after'])
    sender.put([])  # nothing to send: not queued
    assert time.monotonic() - start < 0.5  # the caller was never held by the blocked send
    assert sent == []
    release.set()
    deadline = time.monotonic() + 5.0
    while len(sent) < 5 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)
    assert sent == [['block'], ['poll 49'], ['move b'], ['move a 2'], ['after']]
    assert [str(e) for e in errors] == ['bus off']

    release.clear()
    sender.put(['block'])
    time.sleep(0.05)
    sender.put(['waiting at the stop'])
    sender.stop(timeout_s=0.0)  # not waiting for the send under way
    sender.put(['put after the stop'])
    release.set()
    sender.stop()
    assert sent[-1] == ['block']  # the send under way ends; nothing that waited follows it


def test_send_thread_sends_a_replacing_batch_after_everything_put_before_it():
    """A newer target for two modules replaces the waiting one, but goes out after a target for
    one of them that was put in between: the last target put for each module is the one it gets."""
    sent = []
    release = threading.Event()

    def send(frames):
        if frames == ['block']:
            release.wait(5.0)
        sent.append(frames)

    sender = SendThread(send, print)
    sender.put(['block'])
    time.sleep(0.05)  # the thread is in that send now
    sender.put(['a=1', 'b=1'], key=('a', 'b'))
    sender.put(['a=2'], key=('a',))
    sender.put(['a=3', 'b=3'], key=('a', 'b'))
    release.set()
    deadline = time.monotonic() + 5.0
    while len(sent) < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.05)
    sender.stop()
    assert sent == [['block'], ['a=2'], ['a=3', 'b=3']]


def test_struct_layouts_agree_with_cantools():
    dbc = load_dbc(config_path('krang_can.dbc'))
    rng = random.Random(0)
    for message in dbc.messages:
        layout = FrameLayout(message)
        for _ in range(50):
            values = {
                s.name: rng.randint(
                    -(1 << (s.length - 1)) if s.is_signed else 0,
                    (1 << (s.length - 1)) - 1 if s.is_signed else (1 << s.length) - 1,
                )
                for s in message.signals
            }
            data = layout.encode(values)
            assert data == message.encode(values, scaling=False, strict=True)
            assert layout.decode(data) == message.decode(data, scaling=False)
        first = message.signals[0]
        too_big = (1 << (first.length - (1 if first.is_signed else 0))) + 1
        with pytest.raises(ValueOutOfRange):
            layout.encode({s.name: 0 for s in message.signals} | {first.name: too_big})
