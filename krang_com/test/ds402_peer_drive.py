"""An independent peer for the bridge: AMC-like DS402 drives as canopen LocalNodes, own process.

Written from docs/can.md and the CiA 301/402 objects, not with krang_can_bridge's codecs or
emulators (frames are packed with struct), so that the bridge is tested against a second reading
of the protocol. Each drive:
- answers SDO (canopen LocalNode) for the objects the bridge's start-up touches and follows NMT;
- runs the DS402 state machine on the controlword (SDO 0x6040 or the AMC current RPDO
  0x200 + 7 node + 2); a fault reset acts on the rising edge of bit 7 and only once the fault's
  cause is gone; RPDOs count only in OPERATIONAL;
- is a heartbeat consumer (0x1016.1 = producer node id << 16 | ms, as the bridge wrote it): it
  starts watching at the first heartbeat and, when none came for that long, applies the abort
  connection option 0x6007 (1 fault + EMCY 0x8130, 2 disable voltage, 3 quick stop);
- applies the target current only in OPERATIONAL, OPERATION_ENABLED and current mode (4);
- sends its TPDOs (position, velocity, current, statusword) while OPERATIONAL, every timer 1
  cycle (0x2120, ms, as the host wrote it; 0, the power-on value, sends none).

SIGUSR1 puts the --fault-node drive into FAULT with an EMCY (0x2310, over-current) while its cause
stays; SIGUSR2 removes the cause (the drive stays in FAULT until a fault reset). Lines on stdin:
- `reboot`: the --fault-node drive power-cycles (a brown-out): its object dictionary back to the
  defaults (no TPDO timer, no heartbeat consumer, abort option 1), DS402 SWITCH_ON_DISABLED, the
  DS301 boot-up message, then NMT PRE-OPERATIONAL;
- `freeze counter` / `freeze values` / `thaw`: the DMU (--dmu) goes on sending at its rate, either
  its last frames again (sequence counter stuck, same values) or the same values with an
  advancing counter; `thaw` makes it live again;
- `silence BUS:ID` / `answer BUS:ID`: that PowerCube module (--modules) stops answering (it goes
  on holding its position, and still reports the motions it is sent) or answers again.

With --modules BUS=CHANNEL:PORT:ID,ID,... (repeated) it is also the PowerCube modules on that bus
(Amtec's protocol, docs/can.md): GET_PARAM ACT_FPOS 0x3C / ACT_FVEL 0x41 on 0x0C0 + id answered
on 0x0A0 + id with the float32; SET_PARAM acknowledged [0x08][param][0]; SET_MOTION FRAMP 14 runs
to its target at the TARGET_VEL 0x4F last set, acknowledged with the position and a short state;
RESET acknowledged. Each FRAMP is printed (module, target), so a test sees which modules are
commanded.

With --dmu CHANNEL:PORT it is also a DMU on that bus: the angular-rate frame 0x40 and the
acceleration frame 0x50 (int16 x, y, z, u8 status, u8 sequence, little-endian; docs/can.md) every
--dmu-period-ms, from the raw values --dmu-raw (six int16: rates x y z, accelerations x y z) plus
+-2 LSB of noise on each, as a real sensor's noise makes every sample differ.

Every change of a drive's applied current or state is printed as a JSON line with its
time.monotonic() (one clock for all processes of the machine), so a test can time what the drive
did.

    python ds402_peer_drive.py --channel 239.74.1.4 --port 45000 --nodes 32:1,33:-1
"""

import argparse
import json
import random
import signal
import struct
import sys
import threading
import time

import can
import canopen
from canopen import objectdictionary as od

KP_DEFAULT, KI_DEFAULT, KS_DEFAULT = 600, 1, 20000  # docs/can.md: 60 A peak, k_i 1, 20 kHz
WATCH_PERIOD_S = 0.002
EMCY_HEARTBEAT_LOST, EMCY_OVER_CURRENT = 0x8130, 0x2310

STATUSWORD = {
    'SWITCH_ON_DISABLED': 0x0040,
    'READY_TO_SWITCH_ON': 0x0021,
    'SWITCHED_ON': 0x0023,
    'OPERATION_ENABLED': 0x0027,
    'QUICK_STOP_ACTIVE': 0x0007,
    'FAULT': 0x0008,
}

_print_lock = threading.Lock()


def emit(**event):
    with _print_lock:
        print(json.dumps({'t': time.monotonic(), **event}), flush=True)


def _var(index, subindex, data_type, default, access='rw'):
    v = od.ODVariable(f'0x{index:04X}.{subindex}', index, subindex)
    v.data_type, v.access_type, v.default = data_type, access, default
    return v


def _record(index, subs):
    rec = od.ODRecord(f'0x{index:04X}', index)
    rec.add_member(_var(index, 0, od.UNSIGNED8, max(s.subindex for s in subs), 'ro'))
    for s in subs:
        rec.add_member(s)
    return rec


def dictionary(node_id, kp, k_i, k_s):
    d = od.ObjectDictionary()
    d.node_id = node_id
    for index, dtype, default in (
        (0x1017, od.UNSIGNED16, 0),
        (0x100C, od.UNSIGNED16, 0),
        (0x100D, od.UNSIGNED8, 0),
        (0x6040, od.UNSIGNED16, 0),
        (0x6041, od.UNSIGNED16, 0x40),
        (0x6060, od.INTEGER8, 0),
        (0x6061, od.INTEGER8, 0),
        (0x6007, od.INTEGER16, 1),
        (0x2120, od.UNSIGNED32, 0),
        (0x2121, od.UNSIGNED32, 0),
    ):
        d.add_object(_var(index, 0, dtype, default))
    d.add_object(_record(0x1016, [_var(0x1016, 1, od.UNSIGNED32, 0)]))
    d.add_object(
        _record(
            0x20D8,
            [
                _var(0x20D8, 0x0C, od.UNSIGNED16, kp, 'ro'),
                _var(0x20D8, 0x24, od.UNSIGNED32, round(k_s / 1000 * 65536), 'ro'),
            ],
        )
    )
    d.add_object(_record(0x2032, [_var(0x2032, 0x08, od.UNSIGNED16, k_i, 'ro')]))
    for index in (0x1402, 0x1403, 0x1404, 0x1800, 0x1802, 0x1803, 0x1804):
        d.add_object(
            _record(
                index,
                [_var(index, 1, od.UNSIGNED32, 0x80000000), _var(index, 2, od.UNSIGNED8, 0xFE)],
            )
        )
        # AMC's fixed mappings (canopen's PDO classes need a mapping object per PDO)
        d.add_object(_record(index + 0x200, [_var(index + 0x200, 1, od.UNSIGNED32, 0, 'ro')]))
    return d


class Drive:
    def __init__(self, network, node_id, sign, kp, k_i, k_s):
        self.id, self.sign, self.kp = node_id, sign, kp
        self.lock = threading.RLock()
        self.state, self.mode, self.last_cw = 'SWITCH_ON_DISABLED', 0, 0
        self.target_a = 0.0
        self.fault_cause = False
        self.consumer = None  # (producer id, timeout s) from 0x1016.1
        self.last_heartbeat = None  # watching starts at the first heartbeat
        self.abort_option = 1
        self.tpdo_period_s = 0.0  # timer 1 off until the host sets its cycle
        self.next_tpdo = 0.0
        self.node = canopen.LocalNode(node_id, dictionary(node_id, kp, k_i, k_s))
        self.node.add_write_callback(self.on_write)
        self.node.add_read_callback(self.on_read)
        network.add_node(self.node)
        network.subscribe(0x200 + 7 * node_id + 2, self.on_rpdo_current)
        self.network = network
        self._reported = None
        self.node.nmt.send_command(0x81)  # boot-up, then pre-operational
        self.node.nmt.send_command(0x80)
        self.report()

    # ---- what the drive does ----
    def applied_a(self):
        on = (
            self.node.nmt.state == 'OPERATIONAL'
            and self.state == 'OPERATION_ENABLED'
            and self.mode == 4
        )
        return self.target_a if on else 0.0

    def report(self, why=''):
        now = (self.state, self.applied_a(), self.node.nmt.state)
        if now != self._reported:
            self._reported = now
            emit(node=self.id, state=self.state, nmt=now[2], amps=now[1], why=why)

    def controlword(self, cw):
        rising_reset = bool(cw & 0x80) and not self.last_cw & 0x80
        self.last_cw = cw
        s = self.state
        if s == 'FAULT':
            if rising_reset and not self.fault_cause:
                self.state = 'SWITCH_ON_DISABLED'
        elif not cw & 0x02:
            self.state = 'SWITCH_ON_DISABLED'
        elif not cw & 0x04:
            self.state = 'QUICK_STOP_ACTIVE' if s == 'OPERATION_ENABLED' else 'SWITCH_ON_DISABLED'
        elif not cw & 0x01:
            if s in ('SWITCH_ON_DISABLED', 'SWITCHED_ON', 'OPERATION_ENABLED'):
                self.state = 'READY_TO_SWITCH_ON'
        elif not cw & 0x08:
            if s in ('READY_TO_SWITCH_ON', 'OPERATION_ENABLED'):
                self.state = 'SWITCHED_ON'
        elif s in ('SWITCHED_ON', 'QUICK_STOP_ACTIVE'):
            self.state = 'OPERATION_ENABLED'

    def fault(self, code, why):
        self.state = 'FAULT'
        self.node.emcy.send(code, 0x01)
        self.report(why)

    # ---- CAN ----
    def on_write(self, index, subindex, od, data):
        value = od.decode_raw(data)
        with self.lock:
            if index == 0x6040:
                self.controlword(value)
            elif index == 0x6060:
                self.mode = value
            elif index == 0x6007:
                self.abort_option = value
                emit(node=self.id, event='sdo', index=index, value=value)
            elif index == 0x2120:
                self.tpdo_period_s = value / 1000.0
                emit(node=self.id, event='tpdo timer', ms=value)
            elif index == 0x1016 and subindex == 1:
                producer, ms = value >> 16 & 0x7F, value & 0xFFFF
                if self.consumer is not None:
                    self.network.unsubscribe(0x700 + self.consumer[0], self.on_heartbeat)
                self.consumer = (producer, ms / 1000.0) if ms else None
                self.last_heartbeat = None
                if ms:
                    self.network.subscribe(0x700 + producer, self.on_heartbeat)
                emit(node=self.id, event='sdo', index=index, value=value)
            self.report(f'SDO 0x{index:04X}')

    def reboot(self):
        """A power cycle: everything the host wrote is gone, the drive boots again."""
        with self.lock:
            if self.consumer is not None:
                self.network.unsubscribe(0x700 + self.consumer[0], self.on_heartbeat)
            self.node.data_store = {}
            self.state, self.mode, self.last_cw, self.target_a = 'SWITCH_ON_DISABLED', 0, 0, 0.0
            self.consumer, self.last_heartbeat, self.abort_option = None, None, 1
            self.tpdo_period_s, self.fault_cause = 0.0, False
            emit(node=self.id, event='rebooted')
            self.node.nmt.send_command(0x81)  # boot-up, then pre-operational
            self.node.nmt.send_command(0x80)
            self.report('reboot')

    def on_read(self, index, subindex, od):
        if index == 0x6041:
            return STATUSWORD[self.state]
        return None

    def on_rpdo_current(self, can_id, data, timestamp):
        with self.lock:
            if self.node.nmt.state != 'OPERATIONAL' or len(data) != 4:
                return
            cw, dc2 = struct.unpack('<Hh', bytes(data))
            self.controlword(cw)
            self.target_a = self.sign * dc2 * (self.kp / 10) / 2**15
            self.report('RPDO')

    def on_heartbeat(self, can_id, data, timestamp):
        with self.lock:
            self.last_heartbeat = time.monotonic()

    def watch(self, now):
        """The heartbeat consumer's timer (DS301), then 0x6007 on expiry (DS402)."""
        with self.lock:
            self.report('NMT')
            if self.consumer is None or self.last_heartbeat is None:
                return
            if now - self.last_heartbeat <= self.consumer[1]:
                return
            self.last_heartbeat = None  # watching again at the next beat
            emit(node=self.id, event='heartbeat lost', option=self.abort_option)
            if self.abort_option == 1:
                self.fault(EMCY_HEARTBEAT_LOST, 'heartbeat lost')
            elif self.abort_option == 2:
                self.state = 'SWITCH_ON_DISABLED'
            elif self.abort_option == 3 and self.state == 'OPERATION_ENABLED':
                self.state = 'QUICK_STOP_ACTIVE'
            self.report('heartbeat lost')

    def tpdos(self, now):
        """The TPDO set when timer 1 is due at `now`, else nothing."""
        with self.lock:
            if not self.tpdo_period_s or now < self.next_tpdo:
                return []
            self.next_tpdo = max(self.next_tpdo + self.tpdo_period_s, now)
            if self.node.nmt.state != 'OPERATIONAL':
                return []
            sw = STATUSWORD[self.state]
            dc1 = round(self.sign * self.applied_a() / (self.kp / 10) * 2**13)
        base = 0x200 + 7 * self.id
        return [
            (base + 3, struct.pack('<Hi', sw, 0)),
            (base + 4, struct.pack('<Hi', sw, 0)),
            (base + 5, struct.pack('<Hh', sw, dc1)),
            (base + 6, struct.pack('<H', sw)),
        ]


class Module:
    """A PowerCube module: position and the FRAMP it runs (module docstring)."""

    def __init__(self, name, module_id, position):
        self.name, self.id = name, module_id
        self.position, self.target, self.speed, self.velocity = position, position, 0.5, 0.0
        self.answering = True

    def step(self, dt):
        error = self.target - self.position
        step = max(-self.speed * dt, min(self.speed * dt, error))
        self.position += step
        self.velocity = step / dt if dt > 0 else 0.0

    def reply(self, data):
        """The acknowledgement of one host frame's data, or None."""
        cmd = data[0]
        if cmd == 0x0A and len(data) == 2 and data[1] in (0x3C, 0x41):
            value = self.position if data[1] == 0x3C else self.velocity
            return bytes([0x0A, data[1]]) + struct.pack('<f', value)
        if cmd == 0x08 and len(data) == 6:
            if data[1] == 0x4F:
                self.speed = struct.unpack('<f', data[2:6])[0]
            return bytes([0x08, data[1], 0])
        if cmd == 0x0B and len(data) == 6 and data[1] == 14:
            self.target = struct.unpack('<f', data[2:6])[0]
            emit(module=self.name, event='framp', target=self.target, answering=self.answering)
            return bytes([0x0B, 14]) + struct.pack('<f', self.position) + bytes([0, 0])
        if cmd == 0x00 and len(data) == 1:
            return bytes([0x00])
        return None


class ModuleBus:
    """The PowerCube modules of one bus, answering from their own thread."""

    def __init__(self, name, channel, port, ids, lock):
        self.bus = can.Bus(interface='udp_multicast', channel=channel, port=port)
        self.modules = {i: Module(f'{name}:{i}', i, 0.01 * i) for i in ids}
        self.lock, self.last = lock, time.monotonic()
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self):
        while True:
            try:
                msg = self.bus.recv(0.1)
            except Exception:  # noqa: BLE001 - the bus is shut down at exit
                return
            if msg is None or not 0x0C0 <= msg.arbitration_id <= 0x0FF:
                continue
            module = self.modules.get(msg.arbitration_id & 0x1F)
            if module is None:
                continue
            with self.lock:
                data = module.reply(bytes(msg.data))
                answering = module.answering
            if data is not None and answering:
                self.bus.send(
                    can.Message(arbitration_id=0x0A0 + module.id, data=data, is_extended_id=False)
                )

    def step(self, now):
        with self.lock:
            for module in self.modules.values():
                module.step(now - self.last)
        self.last = now


class Dmu:
    """The DMU: 0x40 and 0x50 every period, live, or frozen as asked (module docstring)."""

    def __init__(self, bus, period_s, raw):
        self.bus, self.period_s, self.raw = bus, period_s, raw
        self.mode, self.sequence, self.next_at = 'live', 0, time.monotonic()
        self.last = None
        self.rng = random.Random()

    def frames(self, now):
        if now < self.next_at:
            return []
        self.next_at = max(self.next_at + self.period_s, now)
        if self.mode == 'counter' and self.last is not None:
            return self.last  # the same frames again
        if self.mode == 'values' and self.last is not None:
            values = self.values
        else:
            values = [v + self.rng.randint(-2, 2) for v in self.raw]
        self.values, seq = values, self.sequence
        self.sequence = (self.sequence + 1) & 0xFF
        self.last = [
            (0x40, struct.pack('<hhhBB', *values[:3], 0, seq)),
            (0x50, struct.pack('<hhhBB', *values[3:], 0, seq)),
        ]
        return self.last

    def send(self, now):
        for cob, data in self.frames(now):
            self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))


def read_commands(commands):
    """Lines on stdin, one command each (module docstring)."""
    for line in sys.stdin:
        if line.strip():
            commands.append(line.strip())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--channel', required=True)
    ap.add_argument('--port', type=int, required=True)
    ap.add_argument('--nodes', default='32:1,33:-1', help='node_id:sign,...')
    ap.add_argument('--fault-node', type=int, default=33)
    ap.add_argument('--kp', type=int, default=KP_DEFAULT)
    ap.add_argument('--ki', type=int, default=KI_DEFAULT)
    ap.add_argument('--ks', type=int, default=KS_DEFAULT)
    ap.add_argument('--dmu', help='CHANNEL:PORT of the DMU bus (none: no DMU)')
    ap.add_argument('--dmu-period-ms', type=float, default=5.0)
    ap.add_argument('--dmu-raw', help='six int16: rates x y z, accelerations x y z')
    ap.add_argument(
        '--modules', action='append', default=[], help='BUS=CHANNEL:PORT:ID,ID,... (repeated)'
    )
    args = ap.parse_args()
    network = canopen.Network()
    network.connect(interface='udp_multicast', channel=args.channel, port=args.port)
    drives = {}
    for item in args.nodes.split(','):
        node_id, sign = (int(x, 0) for x in item.split(':'))
        drives[node_id] = Drive(network, node_id, sign, args.kp, args.ki, args.ks)
    dmu = None
    if args.dmu:
        channel, port = args.dmu.rsplit(':', 1)
        dmu_bus = can.Bus(interface='udp_multicast', channel=channel, port=int(port))
        raw = [int(x) for x in args.dmu_raw.split(',')]
        dmu = Dmu(dmu_bus, args.dmu_period_ms / 1000.0, raw)
    module_lock, module_buses = threading.Lock(), {}
    for item in args.modules:
        name, where = item.split('=', 1)
        channel, port, ids = where.rsplit(':', 2)
        module_buses[name] = ModuleBus(
            name, channel, int(port), [int(i) for i in ids.split(',')], module_lock
        )
    requests, commands = [], []
    signal.signal(signal.SIGUSR1, lambda *_: requests.append('fault'))
    signal.signal(signal.SIGUSR2, lambda *_: requests.append('clear'))
    threading.Thread(target=read_commands, args=(commands,), daemon=True).start()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    emit(event='ready')
    try:
        while not stop.is_set():
            now = time.monotonic()
            while requests:
                drive = drives[args.fault_node]
                with drive.lock:
                    if requests.pop(0) == 'fault':
                        drive.fault_cause = True
                        drive.fault(EMCY_OVER_CURRENT, 'injected fault')
                    else:
                        drive.fault_cause = False
                        emit(node=drive.id, event='fault cause removed')
            while commands:
                command = commands.pop(0)
                if command == 'reboot':
                    drives[args.fault_node].reboot()
                elif dmu is not None and command.startswith(('freeze', 'thaw')):
                    dmu.mode = command.split()[1] if command != 'thaw' else 'live'
                    emit(event='dmu', mode=dmu.mode)
                elif command.startswith(('silence ', 'answer ')):
                    verb, where = command.split()
                    name, module_id = where.rsplit(':', 1)
                    with module_lock:
                        module_buses[name].modules[int(module_id)].answering = verb == 'answer'
                    emit(event=verb, module=where)
            if dmu is not None:
                dmu.send(now)
            for module_bus in module_buses.values():
                module_bus.step(now)
            for drive in drives.values():
                drive.watch(now)
            for drive in drives.values():
                for cob, data in drive.tpdos(now):
                    network.send_message(cob, data)
            time.sleep(WATCH_PERIOD_S)
    finally:
        network.disconnect()
        if dmu is not None:
            dmu.bus.shutdown()
        for module_bus in module_buses.values():
            module_bus.bus.shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
