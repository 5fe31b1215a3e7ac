"""The robot's CAN devices in two processes of their own, for `bench_ros_latency.py --robot`.

It plays the buses of a device map (udp_multicast, e.g. krang_sim.session_config's private ports)
with the emulators of krang_sim/devices.py, which speak through the bridge's own codecs: the DMU
streams samples (0x40 rates + 0x50 accelerations, sequence counters) at --rate-hz, the AMC drives
answer the bridge's start-up SDOs and send their TPDOs at the timer cycle the bridge wrote to them
(wheels.tpdo_period_ms of the bridge's device map; none before), the PowerCube modules answer
the polls. There is no physics: the robot sits on its caster (the drive train's caster pitch)
and, on the command `stand`, pitches up to the nominal model's balance pitch in --ramp-s
(a cosine ramp, the wheels rolling back so that the axle stays put), then holds it, with white
gyro and accelerometer noise so that every sample gives a different wheel command.

It also plays the reference chain's end, while told to: a frame 0x7E0 carrying a counter on its
own bus (--ref-port) at --rate-hz, answered by 0x7E1 with the same counter (bench/ref_chain.py),
and meanwhile the TPDO sets the drives will send once started (wheels.tpdo_period_ms of the map),
so that the reference is measured beside the same player load and bus traffic as the nodes.

Each process plays part of them (--play, see PLAYS): `dmu` the DMU, `rest` the drives, the
PowerCube modules and the reference chain's end. Each writes what it played to its own record,
and their periods keep their phases.

A CAN bus carries one frame at a time: at --bitrate (Krang's nets run at 1 Mbit/s, docs/can.md) the
two drives' TPDO sets, eight frames, take 0.66 ms of the wire (a DMU sample 0.22 ms), and a frame
cannot start before the one ahead of it has ended. The player's periodic frames (the DMU's samples,
the TPDO sets) keep that spacing (Wire), where a udp_multicast socket would carry them in one burst
no bus can; its replies (SDO, PowerCube) go at once. The spacing is each frame's length without
stuff bits (which add up to a fifth), so the player's frames come no later than the bus would carry
them; frames of the other process and of the host are not serialised with them.

Every time is the kernel's receive stamp of the frame on this process's own socket (the player
hears its own frames too), so the figures are those of the bus. Commands on stdin, one a line:
`stand`, `sit` (back on the caster at once), `probe` (from now on every --probe-every th sample
is a probe, see below), `ref` / `noref` (start / stop the reference frames), `quit` (write --out
and exit). Prints `ready` once the buses are open.

Probes: the sample is sent with its pitch rate raised by --probe-rad-s and the following
--probe-every - 1 samples lowered by a share of it each, so that the integrated pitch is
unchanged; successive probes alternate in sign. The wheel command that answers a probe is the
first one that moves with it by more than half the probes' response, which the other samples
never do and the next probe does the other way, so a probe carries its identity into the command
even when the answer comes later than the next samples (bench_ros_latency.py).
"""

import argparse
import heapq
import itertools
import math
import resource
import sys
import threading
import time

import can
import numpy as np

from krang_can_bridge.bus_io import BusReader, enlarge_receive_buffer, receive_only
from krang_can_bridge.config import load_devices
from krang_can_bridge.protocols import load_dbc
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols.dmu_imu import ACCELERATIONS_ID
from krang_model.com import balance_pitch
from krang_model.config import load_config
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_ros.entry import settle_garbage_collector
from krang_sim.devices import KrangCanDevices

REF_REQUEST_ID, REF_ANSWER_ID = 0x7E0, 0x7E1
REF = 'ref'  # the reference chain's bus
#: What a player process plays (--play): its jobs. The benchmark runs the DMU in a process of its
#: own: one Python process playing every device delayed the DMU's samples behind the drives' work
#: (its jobs cost 0.2 ms of CPU each, a few a second 3-6 ms; it was 8-20 ms late about 1.5 times
#: a second), which a DMU, a device with its own processor and clock, never is.
PLAYS = {'dmu': ('dmu',), 'rest': ('ref', 'tpdo')}
GYRO_NOISE_RAD_S = 0.001  # about 7 LSB of the DMU
ACCEL_NOISE_M_S2 = 0.002
#: A DMU or a drive never drops a period. A frame this process sends late (descheduled on the
#: shared cores, or in a slow send: the Python player's jobs cost 0.2 ms of CPU each, and a few a
#: second 3-6 ms) goes out late and in order, like a frame that waited in a device's transmit
#: queue while the bus was busy; only a stall longer than this many periods (100 ms at 500 Hz) is
#: skipped. With 5 (10 ms) the player's stalls of 8-20 ms, about 1.5 a second, cost 4-12 of the
#: 500 samples a second (488-496 played), and the control rate of bench_ros_latency.py measured
#: the player, not the nodes; every sample's lateness is in the record (`sample_late`).
CATCH_UP_PERIODS = 50
TIMER_POLL_S = 0.01  # how often the player looks whether the bridge has set the TPDO timer


def next_due(due, period, now):
    """When the period after the one due at `due` is due: late periods are still played, late and
    in order, unless `now` is more than CATCH_UP_PERIODS past it (then the missed ones are
    skipped)."""
    due += period
    behind = now - due
    if behind > CATCH_UP_PERIODS * period:
        due += math.ceil(behind / period) * period
    return due


def frame_bits(msg):
    """Bits a CAN 2.0 data frame occupies on the wire, without stuff bits: start of frame,
    identifier (11 or 29 bits with SRR and IDE), control, data, CRC, acknowledgement, end of
    frame and the 3-bit interframe space."""
    return (67 if msg.is_extended_id else 47) + 8 * len(msg.data)


class Wire:
    """The buses' serialisation: each bus carries one frame at a time, at `bitrate` bits a second
    (0: no spacing). `add` schedules frames in order; `due` says when the next one may go, and
    `take` hands over those whose time has come."""

    def __init__(self, bitrate):
        self.bit_s = 1.0 / bitrate if bitrate else 0.0
        self.free = {}  # bus name -> when the frame on it ends
        self.queue = []  # heap of (start, order, frame)
        self.order = itertools.count()

    def add(self, frames, now):
        for f in frames:
            start = max(now, self.free.get(f.bus, now))
            self.free[f.bus] = start + frame_bits(f.msg) * self.bit_s
            heapq.heappush(self.queue, (start, next(self.order), f))

    def due(self):
        return self.queue[0][0] if self.queue else math.inf

    def take(self, now):
        out = []
        while self.queue and self.queue[0][0] <= now:
            out.append(heapq.heappop(self.queue)[2])
        return out


def bench_pose():
    """The Table II upper-body pose the simulated robot starts in (sim_params.yaml), as a dict."""
    robot = load_krang()
    pose = load_config('sim_params.yaml')['sim_krang']['ros__parameters']['initial_pose']
    return robot, dict(zip(robot.pose_joints, pose))


class Pitch:
    """The played pitch trajectory: sitting, then a cosine ramp to `target` over `ramp_s`."""

    def __init__(self, sit, target, ramp_s):
        self.sit, self.target, self.ramp_s = sit, target, ramp_s
        self.start = None

    def at(self, t):
        if self.start is None or t <= self.start:
            return self.sit, 0.0
        s = (t - self.start) / self.ramp_s
        if s >= 1.0:
            return self.target, 0.0
        d = self.target - self.sit
        return (
            self.sit + d * 0.5 * (1.0 - math.cos(math.pi * s)),
            d * 0.5 * math.pi * math.sin(math.pi * s) / self.ramp_s,
        )


class Player:
    def __init__(self, args):
        self.args = args
        config = load_devices(args.devices)
        self.config = config
        self.robot, joints = bench_pose()
        self.devices = KrangCanDevices(
            config,
            initial_joint_positions=joints,
            imu_rate_noise_std_rad_s=GYRO_NOISE_RAD_S,
            imu_accel_noise_std_m_s2=ACCEL_NOISE_M_S2,
            seed=args.seed,
        )
        # While the reference chain plays, the drives are not yet started and send nothing: these
        # enabled twins send the same TPDO sets at the device map's period instead, so that both
        # chains are measured beside the same player load and the same frames on the buses.
        self.stand_in = KrangCanDevices(config, auto_enable_wheels=True)
        # sitting on the caster, then up to where the nominal model's CoM is over the axle
        self.sit_pitch = drivetrain(self.robot).caster_contact_pitch
        q = np.array([[joints[j] for j in self.robot.pose_joints]])
        stand_pitch = float(balance_pitch(self.robot, q, self.robot.nominal_beta)[0])
        self.pitch = Pitch(self.sit_pitch, stand_pitch, args.ramp_s)
        dbc = load_dbc(config.dbc_path)
        rpdo = amc_proto.RPDO_CURRENT
        self.drives = config.wheels.drives
        self.rpdo_ids = {
            amc_proto.AmcDriveCodec(d, config.wheels, dbc).ids[rpdo]: d.joint for d in self.drives
        }
        self.plays = PLAYS[args.play]
        names = [config.imu.bus] if self.plays == ('dmu',) else config.buses_in_use()
        self.buses = {n: can.Bus(**config.buses[n].bus_kwargs()) for n in names}
        for name, bus in self.buses.items():
            receive_only(bus, self.heard_ids(name))
        if 'ref' in self.plays:
            self.buses[REF] = can.Bus(
                interface='udp_multicast', channel=args.ref_channel, port=args.ref_port
            )
            receive_only(self.buses[REF], (REF_REQUEST_ID, REF_ANSWER_ID))
        for bus in self.buses.values():
            # it hears its own frames too: the bus_io queue outlasts a stall of its receive thread
            enlarge_receive_buffer(bus)
        self.wire = Wire(args.bitrate)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.probing = False
        self.playing_ref = False
        self.probe_sign = -1  # probes alternate in sign, the first is positive
        self.samples = []  # (kernel time of the 0x50 frame, sequence)
        self.sent = []  # (sequence, probe sign or 0, seconds late) of every sample sent, in order
        self.commands = []  # (kernel time, RPDO id, DC2 raw value)
        self.tpdo_sent = []  # time.time() of each TPDO set sent (real or stand-in drives)
        self.ref = {REF_REQUEST_ID: [], REF_ANSWER_ID: []}  # (kernel time, counter)

    # ---- receive -------------------------------------------------------------------------------
    def heard_ids(self, bus):
        """What the player reads on `bus` (the kernel drops the rest, above all the echoes of its
        own TPDOs and replies): the host's frames to the devices it answers, and the echo of the
        DMU's 0x50 if it plays the DMU (the sample's time on the bus)."""
        ids = self.devices.host_ids(bus) if 'tpdo' in self.plays else set()
        dmu = 'dmu' in self.plays and bus == self.config.imu.bus
        return ids | {ACCELERATIONS_ID} if dmu else ids

    def receive(self, name, msg):
        aid = msg.arbitration_id
        if name == REF:
            if len(msg.data) == 4:
                self.ref[aid].append((msg.timestamp, int.from_bytes(msg.data, 'little')))
            return
        if aid == ACCELERATIONS_ID:
            self.samples.append((msg.timestamp, msg.data[7]))
            return
        if aid in self.rpdo_ids and len(msg.data) == 4:
            self.commands.append(
                (msg.timestamp, aid, int.from_bytes(msg.data[2:4], 'little', signed=True))
            )
        with self.lock:
            replies = self.devices.on_frame(name, msg)
        for reply in replies:
            self.buses[reply.bus].send(reply.msg)

    def receive_error(self, name, exc):
        print(f'device player: receive on {name} failed: {exc}', file=sys.stderr)

    def commands_in(self):
        for line in sys.stdin:
            word = line.strip()
            if word == 'stand':
                self.pitch.start = time.monotonic()
            elif word == 'sit':
                self.pitch.start = None
            elif word == 'probe':
                self.probing = True
            elif word in ('ref', 'noref'):
                self.playing_ref = word == 'ref'
            elif word == 'quit':
                break
        self.stop.set()

    # ---- send ----------------------------------------------------------------------------------
    def send(self, frames):
        """Queue periodic frames on the wire and send those whose time has come (the first at
        once if its bus is free); the loop sends the rest when they are due."""
        now = time.monotonic()
        self.wire.add(frames, now)
        self.send_due(now)

    def send_due(self, now):
        for f in self.wire.take(now):
            self.buses[f.bus].send(f.msg)

    def dmu_sample(self, probe_phase, late):
        q, dq = self.pitch.at(time.monotonic())
        probe = 0
        kick = 0.0
        if self.probing:
            if probe_phase == 0:
                self.probe_sign = -self.probe_sign
                probe = self.probe_sign
            n = self.args.probe_every
            kick = self.probe_sign * self.args.probe_rad_s * (1.0 if probe else -1.0 / (n - 1))
        with self.lock:
            seq = self.devices.imu.sequence
            frames = self.devices.imu_frames_from_pitch(q, dq + kick)
        self.sent.append((seq, probe, late))
        self.send(frames)

    def tpdos(self, dt):
        """Send the drives' TPDO sets; return when to look again: the TPDO timer cycle the host
        wrote to the drives; before it has, the map's period while the reference plays (the
        stand-in drives), else TIMER_POLL_S."""
        q, dq = self.pitch.at(time.monotonic())
        wheel = self.sit_pitch - q  # the axle stays put while the body pitches
        with self.lock:
            self.devices.step(dt)
            periods = {w.tpdo_period_s for w in self.devices.wheels.values()} - {None}
            drives = self.stand_in if self.playing_ref and not periods else self.devices
            frames = drives.wheel_feedback_frames(
                {j: wheel for j in drives.wheels}, {j: -dq for j in drives.wheels}
            )
        if frames:
            self.tpdo_sent.append(time.time())
        self.send(frames)
        if periods:
            return min(periods)
        return self.config.wheels.tpdo_period_ms / 1000.0 if self.playing_ref else TIMER_POLL_S

    def run(self):
        # the sender loop must not wait out Python's 5 ms switch interval behind the receive thread
        sys.setswitchinterval(0.0005)
        reader = BusReader(self.buses, self.receive, self.receive_error)
        threading.Thread(target=self.commands_in, daemon=True).start()
        settle_garbage_collector()  # as the nodes: no full collection pass stalls the samples
        print('ready', flush=True)
        a = self.args
        period = 1.0 / a.rate_hz
        # (next time, period, action): DMU samples, the reference frame a quarter period later,
        # the TPDOs --tpdo-phase periods later (free-running drives land anywhere in the period),
        # at their timer's cycle once the bridge has set it, --tpdo-drift-ppm slower. The DMU's
        # periods start at a multiple of the period on CLOCK_MONOTONIC, which every process
        # shares: players of --play dmu and rest keep these phases.
        start = (math.floor(time.monotonic() / period) + math.ceil(0.1 / period)) * period
        jobs = [
            [start, period, 'dmu'],
            [start + 0.25 * period, period, 'ref'],
            [start + a.tpdo_phase * period, TIMER_POLL_S, 'tpdo'],
        ]
        jobs = [j for j in jobs if j[2] in self.plays]
        k = ref = 0
        while not self.stop.is_set():
            job = min(jobs, key=lambda j: j[0])
            delay = min(job[0], self.wire.due()) - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            now = time.monotonic()
            self.send_due(now)
            if job[0] > now:
                continue
            if job[2] == 'dmu':
                self.dmu_sample(k % a.probe_every, time.monotonic() - job[0])
                k += 1
            elif job[2] == 'ref':
                if self.playing_ref:
                    self.buses[REF].send(
                        can.Message(
                            arbitration_id=REF_REQUEST_ID,
                            is_extended_id=False,
                            data=ref.to_bytes(4, 'little'),
                        )
                    )
                    ref += 1
            else:
                job[1] = self.tpdos(job[1])
            drift = 1.0 + a.tpdo_drift_ppm * 1e-6 if job[2] == 'tpdo' else 1.0
            job[0] = next_due(job[0], job[1] * drift, time.monotonic())
        reader.stop()
        use = resource.getrusage(resource.RUSAGE_SELF)
        print(
            f'device player: {use.ru_utime + use.ru_stime:.1f} s of CPU in '
            f'{time.monotonic() - start:.1f} s',
            file=sys.stderr,
        )
        self.save(a.out)
        for bus in self.buses.values():
            bus.shutdown()

    def save(self, path):
        """The record, with each received sample frame tagged with its probe sign and how late
        it was sent (samples and their echoes are matched in order by sequence counter)."""
        probe = np.zeros(len(self.samples), np.int8)
        late = np.zeros(len(self.samples))
        i = 0
        for n, (_, seq) in enumerate(self.samples):
            while i < len(self.sent) and self.sent[i][0] != seq:
                i += 1
            if i < len(self.sent):
                probe[n], late[n] = self.sent[i][1:]
                i += 1
        cmd = np.array(self.commands, float).reshape(-1, 3)
        np.savez(
            path,
            sample_t=np.array([s[0] for s in self.samples]),
            sample_probe=probe,
            sample_late=late,
            cmd_t=cmd[:, 0],
            cmd_id=cmd[:, 1].astype(int),
            cmd_value=cmd[:, 2],
            left_id=next(i for i, j in self.rpdo_ids.items() if j == 'JLWheel'),
            ref_req=np.array(self.ref[REF_REQUEST_ID], float).reshape(-1, 2),
            ref_ans=np.array(self.ref[REF_ANSWER_ID], float).reshape(-1, 2),
            tpdo_t=np.array(self.tpdo_sent),
        )


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--devices', required=True, help='device map (udp_multicast buses)')
    p.add_argument(
        '--play',
        choices=PLAYS,
        required=True,
        help='the devices this process plays: the DMU, or the rest (the drives, the PowerCube '
        "modules, the reference chain's end); its record has what it played",
    )
    p.add_argument('--ref-channel', default='239.74.163.99')
    p.add_argument('--ref-port', type=int, required=True)
    p.add_argument('--rate-hz', type=float, default=500.0, help='DMU samples per second')
    p.add_argument(
        '--tpdo-phase',
        type=float,
        default=0.5,
        help='the TPDO sets this fraction of a DMU period after the samples, in [0, 1)',
    )
    p.add_argument(
        '--tpdo-drift-ppm',
        type=float,
        default=0.0,
        help="the drives' TPDO timer this many ppm slower than the DMU's clock (their phase "
        'sweeps the sample period: at 100 ppm and 2 ms, once in 20 s)',
    )
    p.add_argument(
        '--bitrate',
        type=float,
        required=True,
        help="the buses' bit rate (bench_ros_latency.BUS_BITRATE): the periodic frames are "
        'spaced by their time on the wire (Wire; 0: sent in bursts)',
    )
    p.add_argument('--ramp-s', type=float, default=1.0)
    p.add_argument('--probe-every', type=int, default=5, help='at least 2')
    p.add_argument('--probe-rad-s', type=float, default=0.03)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--out', required=True, help='record (.npz)')
    Player(p.parse_args()).run()


if __name__ == '__main__':
    main()
