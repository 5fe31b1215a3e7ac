"""BridgeCore: clamping, NaN rejection, silence -> zero current, malformed frames counted, state
decoding.

Device traffic is built by hand with struct from docs/can.md (not with the codecs under test), and
every command frame the core produces is decoded by hand and checked against the limits of
config/can_devices.yaml.
"""

import dataclasses
import math
import random
import struct
import uuid

import can
import canopen
import numpy as np
import pytest
import yaml

from krang_can_bridge import commands, diagnostics, snapshots
from krang_can_bridge.bridge import BridgeCore
from krang_can_bridge.config import ConfigError, load_devices
from krang_can_bridge.protocols import amc_canopen
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

CFG = load_devices()
ADVERSARIAL = [
    math.nan,
    math.inf,
    -math.inf,
    1e308,
    -1e308,
    1e6,
    -1e6,
    0.0,
    -0.0,
    5e-324,
    'nan',
    None,
    '12',
]


def msg(aid, data):
    return can.Message(arbitration_id=aid, data=bytes(data), is_extended_id=False)


class HandDevices:
    """Hand-built device frames: the AMC TPDOs, DMU samples and PowerCube replies of a healthy
    robot."""

    def __init__(self, core, pitch=-0.9):
        self.core, self.pitch, self.seq = core, pitch, 0
        self.module_pos = {
            (m.bus, m.module_id): 0.0 for j in CFG.powercube.joints for m in j.modules
        }

    def feed(self, t, wheels=True, imu=True, modules=True, wheel_counts=(0, 0)):
        c = self.core
        if wheels:
            for d, counts in zip(CFG.wheels.drives, wheel_counts):
                base = 0x200 + 7 * d.node_id
                c.on_frame(msg(base + 3, struct.pack('<Hi', 0x0027, counts)), t, 'can3')
                c.on_frame(msg(base + 4, struct.pack('<Hi', 0x0027, 0)), t, 'can3')
                c.on_frame(msg(base + 6, struct.pack('<H', 0x0027)), t, 'can3')
        if imu:
            m = CFG.imu.mount_angle_rad
            g_lsb = 9.80665 * 0.0003
            f = (
                9.81 * math.sin(self.pitch) * math.cos(m),
                -9.81 * math.sin(self.pitch) * math.sin(m),
                9.81 * math.cos(self.pitch),
            )
            b = CFG.imu.gyro_bias_rad_s
            rates = [round(x / math.radians(0.008)) for x in b]
            c.on_frame(msg(0x40, struct.pack('<hhhBB', *rates, 0, self.seq)), t, 'can3')
            c.on_frame(
                msg(0x50, struct.pack('<hhhBB', *[round(x / g_lsb) for x in f], 0, self.seq)),
                t,
                'can3',
            )
            self.seq = (self.seq + 1) & 0xFF
        if modules:
            for (bus, mid), pos in self.module_pos.items():
                c.on_frame(msg(0x0A0 + mid, bytes([0x0A, 0x3C]) + struct.pack('<f', pos)), t, bus)
                c.on_frame(msg(0x0A0 + mid, bytes([0x0A, 0x41]) + struct.pack('<f', 0.0)), t, bus)


def healthy_core():
    core = BridgeCore(CFG, clock=lambda: 0.0)
    dev = HandDevices(core)
    t = 0.0
    for _ in range(CFG.imu.kalman.init_samples + 20):
        t += 0.002
        dev.feed(t)
    assert core.motion_allowed(t), core.diagnostics(t)[0]
    return core, dev, t


def finite_float(value):
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def wheel_amps_by_hand(frame):
    """Physical current at the joint from an RPDO frame, decoded by hand (DC2, sign from the node
    id)."""
    assert frame.msg.arbitration_id in (0x2E2, 0x2E9) and frame.bus == 'can3'
    cw, dc2 = struct.unpack('<Hh', bytes(frame.msg.data))
    assert cw == 0x008F and len(frame.msg.data) == 4
    drive = CFG.wheels.drive('JLWheel' if frame.msg.arbitration_id == 0x2E2 else 'JRWheel')
    return drive.sign * dc2 * (drive.peak_current_kp / 10) / 2**15


def check_joint_frames_within_limits(frames):
    """Every PowerCube frame, decoded by hand, is inside the configured joint / module limits."""
    modules = {(m.bus, m.module_id): (j, m) for j in CFG.powercube.joints for m in j.modules}
    targets = []
    for f in frames:
        aid, data = f.msg.arbitration_id, bytes(f.msg.data)
        assert 0x0E1 <= aid <= 0x0FF, hex(aid)
        joint, module = modules[(f.bus, aid - 0x0E0)]
        (value,) = struct.unpack('<f', data[2:6])
        assert math.isfinite(value)
        if data[0] == 0x0B:
            assert data[1] == 14 and len(data) == 6
            lo, hi = sorted((module.sign * joint.lower, module.sign * joint.upper))
            assert lo <= value <= hi, (joint.joint, value)
            targets.append((joint.joint, module.sign, value))
        else:
            assert data[0] == 0x08 and data[1] in (0x4F, 0x50)
            limit = joint.max_velocity_rad_s if data[1] == 0x4F else joint.max_acceleration_rad_s2
            assert 0 < value <= limit
    return targets


def test_wheel_effort_to_current_value_and_sign():
    core, _, t = healthy_core()
    effort = 5.0
    drive = drivetrain(load_krang())
    expected = effort / (drive.torque_constant * drive.gear_ratio)
    frames = core.wheel_current_frames(effort, -effort, t)
    assert [f.msg.arbitration_id for f in frames] == [0x2E2, 0x2E9]
    left, right = (wheel_amps_by_hand(f) for f in frames)
    lsb = 60.0 / 2**15
    assert left == pytest.approx(expected, abs=lsb) and right == pytest.approx(-expected, abs=lsb)
    # the right drive sees the opposite raw sign for the same joint-direction current
    same = core.wheel_current_frames(effort, effort, t)
    assert (
        struct.unpack('<Hh', bytes(same[0].msg.data))[1]
        > 0
        > struct.unpack('<Hh', bytes(same[1].msg.data))[1]
    )


def test_wheel_commands_never_exceed_the_limit():
    core, _, t = healthy_core()
    rng = random.Random(1)
    values = (
        ADVERSARIAL
        + [rng.uniform(-500, 500) for _ in range(300)]
        + [rng.gauss(0, 30) for _ in range(300)]
    )
    limit = drivetrain(load_krang()).current_limit
    for left in values:
        right = rng.choice(values)
        frames = core.wheel_current_frames(left, right, t)
        assert len(frames) == 2
        finite = [finite_float(e) is not None for e in (left, right)]
        for f, effort in zip(frames, (left, right)):
            amps = wheel_amps_by_hand(f)
            assert abs(amps) <= limit
            if not all(finite):
                assert amps == 0.0  # either one rejected -> zero on both
            elif abs(float(effort)) > 100:
                assert abs(amps) == pytest.approx(limit, abs=60.0 / 2**15)
    assert core.counters.rejected_commands > 0 and core.counters.clamped_commands > 0


def test_joint_commands_stay_inside_limits():
    core, _, t = healthy_core()
    rng = random.Random(2)
    names = CFG.body_joint_names
    for _ in range(200):
        targets = {
            n: rng.choice([rng.uniform(-20, 20), rng.choice(ADVERSARIAL)])
            for n in rng.sample(names, 6)
        }
        targets['JLWheel'] = 1.0  # not a body joint: ignored
        check_joint_frames_within_limits(core.joint_position_frames(targets, t))
    frames = core.joint_position_frames({'JWaist': 1.5, 'LJ2': math.nan, 'JTorso': 99.0}, t)
    targets = check_joint_frames_within_limits(frames)
    assert ('JWaist', 1, pytest.approx(1.5)) in targets and (
        'JWaist',
        -1,
        pytest.approx(-1.5),
    ) in targets
    assert ('JTorso', 1, pytest.approx(1.57)) in targets
    assert not any(j == 'LJ2' for j, _, _ in targets)  # NaN -> no motion
    assert 'LJ2' in core.counters.last_rejection or core.counters.rejected_commands >= 1
    edge = check_joint_frames_within_limits(
        core.joint_position_frames({'JWaist': 2.88, 'LJ1': -math.pi}, t)
    )
    assert all(abs(v) <= 2.88 for j, _, v in edge if j == 'JWaist')


def test_silent_device_gives_zero_current_within_the_timeout():
    core, dev, t = healthy_core()
    timeout = CFG.wheels.silence_timeout_s
    assert abs(wheel_amps_by_hand(core.wheel_current_frames(20.0, 20.0, t)[0])) > 10
    # the IMU goes quiet; wheels and modules keep talking
    t_quiet = t
    for _ in range(int(timeout / 0.002) + 5):
        t += 0.002
        dev.feed(t, imu=False)
    assert t - t_quiet > CFG.imu.silence_timeout_s
    assert 'imu' in core.silent_devices(t) and not core.motion_allowed(t)
    assert [wheel_amps_by_hand(f) for f in core.wheel_current_frames(20.0, -20.0, t)] == [0.0, 0.0]
    assert core.joint_position_frames({'JTorso': 0.5}, t) == []
    # the silent IMU's last pitch is not passed on as if it were current; the talking devices still
    # are
    assert core.imu_state(t) is None
    assert {'JLWheel', 'JRWheel', 'JWaist'} <= set(core.joint_state(t).names)
    # just inside the timeout a drive is still fine; just after, it is silent
    core2, dev2, t2 = healthy_core()
    assert core2.motion_allowed(t2 + CFG.wheels.silence_timeout_s * 0.9)
    assert not core2.motion_allowed(t2 + CFG.wheels.silence_timeout_s * 1.1)
    assert 'amc/JLWheel' in core2.silent_devices(t2 + CFG.wheels.silence_timeout_s * 1.1)
    assert 'JLWheel' in core2.joint_state(t2 + CFG.wheels.silence_timeout_s * 0.9).names
    assert 'JLWheel' not in core2.joint_state(t2 + CFG.wheels.silence_timeout_s * 1.1).names
    # recovery: traffic again -> motion again
    dev.feed(t + 0.001)
    assert core.motion_allowed(t + 0.001) and core.imu_state(t + 0.001) is not None


def test_nothing_moves_before_every_device_was_heard():
    core = BridgeCore(CFG, clock=lambda: 0.0)
    assert not core.motion_allowed(0.0)
    assert set(core.silent_devices(0.0)) >= {'amc/JLWheel', 'amc/JRWheel', 'imu'}
    assert [wheel_amps_by_hand(f) for f in core.wheel_current_frames(30.0, 30.0, 0.0)] == [
        0.0,
        0.0,
    ]


def test_stale_effort_command_becomes_zero():
    core, dev, t = healthy_core()
    core.set_wheel_effort_command([10.0, 10.0], t)
    assert wheel_amps_by_hand(core.wheel_command_frames(t + 0.01)[0]) > 5
    dev.feed(t + CFG.wheels.command_timeout_s * 0.5)
    later = t + CFG.wheels.command_timeout_s * 1.01
    dev.feed(later)
    assert [wheel_amps_by_hand(f) for f in core.wheel_command_frames(later)] == [0.0, 0.0]


def test_malformed_and_unknown_frames_are_counted_and_survived():
    core, dev, t = healthy_core()
    rng = random.Random(3)
    before = (core.counters.malformed, core.counters.unknown)
    bad = [
        msg(0x2E3, bytes(5)),
        msg(0x40, bytes(7)),
        msg(0x0A4, bytes([0x0A, 0x3C]) + struct.pack('<f', math.nan)),
        msg(0x0A4, bytes([0x0B, 99, 0, 0])),
        msg(0x2E6, bytes(3)),
    ]
    for m in bad:
        core.on_frame(m, t, 'can0' if m.arbitration_id == 0x0A4 else 'can3')
    assert core.counters.malformed == before[0] + len(bad)
    core.on_frame(msg(0x123, bytes(8)), t, 'can3')
    # module 4 is not on can3
    core.on_frame(msg(0x0A4, bytes([0x0A, 0x3C, 0, 0, 0, 0])), t, 'can3')
    assert core.counters.unknown == before[1] + 2
    core.on_frame(can.Message(arbitration_id=0x20000080, is_error_frame=True), t, 'can3')
    assert core.counters.error_frames == {'can3': 1}
    for _ in range(2000):  # fuzz
        data = bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 8)))
        core.on_frame(
            msg(
                rng.choice(
                    [0x40, 0x50, 0x2E3, 0x2E4, 0x2E5, 0x2E6, 0x0A4, 0x0AD, rng.randrange(0x800)]
                ),
                data,
            ),
            t,
            rng.choice(['can0', 'can3', 'can11', 'nonexistent']),
        )
    # our own commands looped back by udp_multicast are neither unknown nor malformed
    n = core.counters.unknown, core.counters.malformed
    for f in core.wheel_current_frames(1.0, 1.0, t) + core.poll_frames() + core.startup_frames():
        core.on_frame(f.msg, t, f.bus)
    assert (core.counters.unknown, core.counters.malformed) == n
    # still decoding correctly afterwards
    dev.module_pos[('can11', 14)] = 1.2
    dev.module_pos[('can11', 15)] = -1.2
    dev.feed(t + 0.001, wheel_counts=(30000, 30000))
    js = dict(zip(core.joint_state().names, core.joint_state().positions))
    # (pos0 - pos1) / 2
    assert js['JWaist'] == pytest.approx(1.2, abs=1e-6)
    assert js['JLWheel'] == pytest.approx(math.pi) and js['JRWheel'] == pytest.approx(-math.pi)


def test_a_moving_joint_is_reported_where_its_polled_speed_has_taken_it():
    """A module speaks only when polled: between polls the bridge reports its joint advanced by
    the polled speed, from the reading's time on and for at most one poll period."""
    core, dev, t = healthy_core()
    (jt,) = [j for j in CFG.powercube.joints if j.joint == 'JTorso']
    (mod,) = jt.modules
    q, v = 0.3, 0.25  # joint coordinates
    read = lambda sel, value: msg(  # noqa: E731
        0x0A0 + mod.module_id, bytes([0x0A, sel]) + struct.pack('<f', mod.sign * value)
    )
    core.on_frame(read(0x3C, q), t, mod.bus)
    core.on_frame(read(0x41, v), t + 0.001, mod.bus)
    period = 1.0 / CFG.powercube.poll_rate_hz

    def torso(now):
        js = core.joint_state(now)
        return dict(zip(js.names, js.positions))['JTorso']

    assert torso(t) == pytest.approx(q, abs=1e-6)
    assert torso(t + 0.02) == pytest.approx(q + 0.02 * v, abs=1e-6)
    assert torso(t + 5 * period) == pytest.approx(q + period * v, abs=1e-6)  # no further
    core.on_frame(read(0x41, 0.0), t + 0.03, mod.bus)  # it stopped
    assert torso(t + 0.04) == pytest.approx(q, abs=1e-6)
    # a silent module is held where it was last read
    core.on_frame(read(0x41, v), t + 0.05, mod.bus)
    late = t + CFG.powercube.silence_timeout_s + 0.1
    assert torso(late) == pytest.approx(q, abs=1e-6)


def test_imu_state_and_stream_toggle():
    core, dev, t = healthy_core()
    imu = core.imu_state()
    assert (
        imu.ready
        and imu.pitch == pytest.approx(-0.9, abs=2e-3)
        and imu.pitch_rate == pytest.approx(0, abs=0.01)
    )
    assert core.imu_stream_frames(t) == []  # streaming: never toggle
    retry = CFG.imu.stream_toggle_retry_s
    frames = core.imu_stream_frames(t + retry + 0.01)
    assert [(f.bus, f.msg.arbitration_id, bytes(f.msg.data)) for f in frames] == [
        ('can3', 0x90, b'\x0f')
    ]
    assert core.imu_stream_frames(t + retry + 0.02) == []  # no toggle storm
    assert len(core.imu_stream_frames(t + 2 * retry + 0.03)) == 1


def test_inhibit_blocks_motion_and_is_reported():
    core, _, t = healthy_core()
    core.inhibit('startup/JLWheel', 'constants mismatch')
    assert not core.motion_allowed(t)
    assert [wheel_amps_by_hand(f) for f in core.wheel_current_frames(10.0, 10.0, t)] == [0.0, 0.0]
    assert 'constants mismatch' in core.diagnostics(t)[0].message
    core.inhibit('startup/JLWheel', None)
    assert core.motion_allowed(t)


# ---- the two wheels are one machine -----------------------------------------------------------
def test_half_invalid_wheel_command_gives_zero_on_both_and_is_reported():
    core, _, t = healthy_core()
    frames = core.wheel_current_frames(math.nan, 20.0, t)
    assert [wheel_amps_by_hand(f) for f in frames] == [0.0, 0.0]
    assert core.counters.rejected_commands == 1
    assert 'JLWheel' in core.counters.last_rejection and 'both' in core.counters.last_rejection
    # the stored command: a rejected one replaces the last valid one by zero on both
    core.set_wheel_effort_command([10.0, 10.0], t)
    assert all(wheel_amps_by_hand(f) > 5 for f in core.wheel_command_frames(t))
    for bad in ([20.0, math.inf], [20.0], [20.0, 20.0, 20.0], [], None, [20.0, 'x']):
        core.set_wheel_effort_command(bad, t)
        assert [wheel_amps_by_hand(f) for f in core.wheel_command_frames(t)] == [0.0, 0.0], bad
    assert core.counters.rejected_commands == 7
    assert 'got 3 values' in core.counters.last_rejection or 'x' in core.counters.last_rejection


def test_fuzzed_half_invalid_pairs_never_drive_one_wheel():
    core, _, t = healthy_core()
    rng = random.Random(10)
    bad = [math.nan, math.inf, -math.inf, None, 'nan', float('-nan')]
    n = 0
    for _ in range(400):
        good = rng.uniform(-300.0, 300.0)
        kind = rng.random()
        if kind < 0.4:
            cmd = [rng.choice(bad), good]
        elif kind < 0.8:
            cmd = [good, rng.choice(bad)]
        else:
            cmd = [good] * rng.choice([0, 1, 3, 4])
        core.set_wheel_effort_command(cmd, t)
        frames = core.wheel_command_frames(t)
        if len(cmd) == 2:
            frames += core.wheel_current_frames(cmd[0], cmd[1], t)
        for pair in (frames[i : i + 2] for i in range(0, len(frames), 2)):
            amps = [wheel_amps_by_hand(f) for f in pair]
            assert amps == [0.0, 0.0], (cmd, amps)  # never one-sided
        n += 1 + (len(cmd) == 2)
    assert core.counters.rejected_commands == n


def test_rejected_commands_make_diagnostics_warn_with_count_and_reason():
    core, _, t = healthy_core()
    report = {r.name: r for r in core.diagnostics(t)}['can_bridge: commands']
    assert report.level == 0 and report.values['rejected_commands'] == '0'
    core.set_wheel_effort_command([math.nan, 20.0], t)
    core.joint_position_frames({'LJ2': math.inf}, t)
    report = {r.name: r for r in core.diagnostics(t + 1.0)}['can_bridge: commands']
    assert report.level == 1 and report.values['rejected_commands'] == '2'
    assert 'LJ2' in report.message and 'LJ2' in report.values['last_rejection']
    later = {r.name: r for r in core.diagnostics(t + diagnostics.REJECTION_WARN_S + 0.1)}
    assert later['can_bridge: commands'].level == 0
    assert '2 rejected' in later['can_bridge: commands'].message


# ---- a faulted drive stops both wheels --------------------------------------------------------
RIGHT = CFG.wheels.drive('JRWheel').node_id


def statusword(core, node_id, sw, t):
    core.on_frame(msg(0x200 + 7 * node_id + 6, struct.pack('<H', sw)), t, 'can3')


def test_drive_fault_statusword_latches_zero_current_on_both_until_recovered():
    core, dev, t = healthy_core()
    assert all(abs(wheel_amps_by_hand(f)) > 10 for f in core.wheel_current_frames(20, 20, t))
    # the leading bytes of the position TPDO are only our reading of AMC's mapping: no decision
    core.on_frame(msg(0x200 + 7 * RIGHT + 3, struct.pack('<Hi', 0x0008, 0)), t, 'can3')
    assert core.fault_reason == ''
    statusword(core, RIGHT, 0x0008, t)  # FAULT
    assert 'JRWheel' in core.fault_reason and 'FAULT' in core.fault_reason
    assert [wheel_amps_by_hand(f) for f in core.wheel_current_frames(20, 20, t)] == [0.0, 0.0]
    assert core.joint_position_frames({'JTorso': 0.3}, t) == []
    motion = core.diagnostics(t)[0]
    assert (
        motion.level == 2
        and 'JRWheel' in motion.message
        and '/can_bridge/recover' in motion.message
    )
    # the drive reporting OPERATION_ENABLED again does not unlatch: only a recover does
    t += 0.01
    dev.feed(t)
    assert core.fault_reason and not core.motion_allowed(t)
    # recovery refused while a drive still reports FAULT after the reset
    since = t
    statusword(core, RIGHT, 0x0008, t + 0.001)
    ok, why = core.recover_status(since)
    assert ok is False and 'JRWheel' in why
    # pending until every drive reported since the enable sequence, then OK
    since = t + 0.002
    assert core.recover_status(since)[0] is None
    dev.feed(t + 0.003)
    assert core.recover_status(since) == (True, '')
    core.clear_fault()
    assert core.fault_reason == '' and core.motion_allowed(t + 0.003)
    assert all(
        abs(wheel_amps_by_hand(f)) > 10 for f in core.wheel_current_frames(20, 20, t + 0.003)
    )


def test_emcy_of_either_drive_latches_a_fault_but_error_reset_does_not():
    core, _, t = healthy_core()
    core.on_frame(msg(0x80 + RIGHT, struct.pack('<HB5s', 0x0000, 0, bytes(5))), t, 'can3')
    assert core.fault_reason == '' and core.motion_allowed(t)
    core.on_frame(msg(0x80 + RIGHT, struct.pack('<HB5s', 0x2310, 0x03, bytes(5))), t, 'can3')
    assert 'JRWheel' in core.fault_reason and '0x2310' in core.fault_reason
    assert [wheel_amps_by_hand(f) for f in core.wheel_current_frames(-20, 20, t)] == [0.0, 0.0]
    core2, _, t2 = healthy_core()
    core2.on_frame(msg(0x80 + 0x20, b'\x01'), t2, 'can3')  # malformed EMCY: a fault too
    assert 'JLWheel' in core2.fault_reason


def test_a_started_drive_leaving_operation_enabled_is_a_fault():
    core, dev, t = healthy_core()
    statusword(core, RIGHT, 0x0040, t)  # not started: start-up transitions are no fault
    assert core.fault_reason == ''
    for joint in CFG.wheel_joint_names:
        core.drive_started(joint, True)
    dev.feed(t + 0.001)  # seen OPERATION_ENABLED: armed
    statusword(core, RIGHT, 0x0040, t + 0.002)  # e.g. its watchdog disabled the voltage
    assert 'left OPERATION_ENABLED' in core.fault_reason
    assert not core.motion_allowed(t + 0.002)


# ---- the drive-side watchdog -------------------------------------------------------------------
def test_heartbeat_only_while_the_command_loop_runs():
    core, _, t = healthy_core()
    wd = CFG.wheels.watchdog
    assert wd.mechanism == 'heartbeat'
    assert core.watchdog_frames(t) == []  # the loop never ran
    core.wheel_command_frames(t)
    frames = core.watchdog_frames(t + wd.alive_timeout_s * 0.9)
    assert [(f.bus, f.msg.arbitration_id, bytes(f.msg.data)) for f in frames] == [
        ('can3', 0x700 + wd.node_id, b'\x05')
    ]
    assert core.watchdog_frames(t + wd.alive_timeout_s * 1.1) == []  # hung loop: no beat
    level = {r.name: r for r in core.diagnostics(t + 1.0)}['can_bridge: drive watchdog'].level
    assert level == 1
    # our own heartbeat looped back is an echo, not an unknown frame
    n = core.counters.unknown
    core.on_frame(frames[0].msg, t, 'can3')
    assert core.counters.unknown == n


def test_guarding_requests_and_no_watchdog():
    guarding = dataclasses.replace(CFG.wheels.watchdog, mechanism='guarding')
    cfg = dataclasses.replace(CFG, wheels=dataclasses.replace(CFG.wheels, watchdog=guarding))
    core = BridgeCore(cfg, clock=lambda: 0.0)
    core.wheel_command_frames(0.0)
    frames = core.watchdog_frames(0.01)
    assert [(f.msg.arbitration_id, f.msg.is_remote_frame) for f in frames] == [
        (0x720, True),
        (0x721, True),
    ]
    off = dataclasses.replace(CFG.wheels.watchdog, mechanism='none')
    core = BridgeCore(
        dataclasses.replace(CFG, wheels=dataclasses.replace(CFG.wheels, watchdog=off))
    )
    core.wheel_command_frames(0.0)
    assert core.watchdog_frames(0.01) == []


def test_startup_configures_the_drive_watchdog_before_the_drive_starts():
    wd = CFG.wheels.watchdog
    steps = amc_canopen.startup_sequence(CFG.wheels.drive('JLWheel'), CFG.wheels)
    keys = [(s.action, s.index, s.subindex, s.value) for s in steps]
    consumer = ('write', 0x1016, 1, (wd.node_id << 16) | round(wd.timeout_s * 1000))
    abort = ('write', 0x6007, 0, wd.abort_connection_option)
    start = ('nmt', 0, 0, 0x01)
    assert keys.index(consumer) < keys.index(start) and keys.index(abort) < keys.index(start)
    guarding = dataclasses.replace(wd, mechanism='guarding')
    keys = [
        (s.index, s.value)
        for s in amc_canopen.startup_sequence(
            CFG.wheels.drive('JLWheel'), dataclasses.replace(CFG.wheels, watchdog=guarding)
        )
    ]
    assert (0x100C, round(wd.period_s * 1000)) in keys
    assert (0x100D, round(wd.timeout_s / wd.period_s)) in keys
    # without a watchdog the sequence is the 2018 one
    none = dataclasses.replace(CFG.wheels, watchdog=dataclasses.replace(wd, mechanism='none'))
    steps = amc_canopen.startup_sequence(CFG.wheels.drive('JLWheel'), none)
    assert steps[-1].value == 0x0F
    assert not {0x1016, 0x100C, 0x100D, 0x6007} & {s.index for s in steps}


@pytest.mark.parametrize(
    'change, complaint',
    [
        ({'mechanism': 'heartbeats'}, 'mechanism'),
        ({'node_id': 0x20}, 'node_id'),
        ({'node_id': 0}, 'node_id'),
        ({'period_s': 0.1}, 'third'),
        ({'abort_connection_option': 4}, '0x6007'),
        ({'alive_timeout_s': 0.005}, 'alive_timeout_s'),
        ({'timeout_s': 70.0}, '65.535'),
        (None, 'watchdog'),
    ],
)
def test_watchdog_settings_are_validated_at_load(tmp_path, change, complaint):
    data = yaml.safe_load(CFG.path.read_text())
    if change is None:
        del data['wheels']['watchdog']
    else:
        data['wheels']['watchdog'].update(change)
    data['dbc_file'] = str(CFG.dbc_path)
    path = tmp_path / 'devices.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=complaint):
        load_devices(path)


@pytest.mark.parametrize(
    'wheels, complaint',
    [
        ({'tpdo_period_ms': 0}, 'whole number'),
        ({'tpdo_period_ms': 2.5}, 'whole number'),
        ({'tpdo_period_ms': True}, 'whole number'),
        ({'tpdo_period_ms': 20}, 'at least 3 TPDO periods'),  # 0.05 s silence timeout
        ({'tpdo_period_ms': 10, 'silence_timeout_s': 0.025}, 'at least 3 TPDO periods'),
        ({'tpdo_period_ms': None}, "missing key 'tpdo_period_ms'"),
    ],
)
def test_tpdo_period_is_validated_at_load(tmp_path, wheels, complaint):
    data = yaml.safe_load(CFG.path.read_text())
    data['wheels'].update(wheels)
    if data['wheels']['tpdo_period_ms'] is None:
        del data['wheels']['tpdo_period_ms']
    data['dbc_file'] = str(CFG.dbc_path)
    path = tmp_path / 'devices.yaml'
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=complaint):
        load_devices(path)
    data['wheels'].update(tpdo_period_ms=16, silence_timeout_s=0.048)  # exactly 3 periods
    path.write_text(yaml.safe_dump(data))
    assert load_devices(path).wheels.tpdo_period_ms == 16


def test_on_frame_reports_each_sample_when_its_frames_are_in():
    """The node publishes on these events: a DMU sample once both of its frames (same sequence
    number) are in; a wheel sample once position, velocity and current of both drives are in. The
    wheels' effort is the measured current as torque at the wheel (Kt x gear)."""
    core, dev, t = healthy_core()
    t += 0.002
    rates = struct.pack('<hhhBB', 0, 0, 0, 0, dev.seq)
    accel = struct.pack('<hhhBB', 0, 0, round(9.81 / (9.80665 * 0.0003)), 0, dev.seq)
    assert core.on_frame(msg(0x40, rates), t, 'can3') is None
    assert core.on_frame(msg(0x50, accel), t, 'can3') == snapshots.IMU_SAMPLE
    assert core.imu_state(t).stamp == t
    events, amps = [], {'JLWheel': 3.0, 'JRWheel': -2.0}
    for d in CFG.wheels.drives:
        base = 0x200 + 7 * d.node_id
        events.append(core.on_frame(msg(base + 3, struct.pack('<Hi', 0x0027, 0)), t, 'can3'))
        events.append(core.on_frame(msg(base + 4, struct.pack('<Hi', 0x0027, 0)), t, 'can3'))
        codec = core.wheel_state(d.joint).codec
        current = codec.encode_actual_current(amps[d.joint], 0x0027)
        events.append(core.on_frame(current, t, 'can3'))
        events.append(core.on_frame(msg(base + 6, struct.pack('<H', 0x0027)), t, 'can3'))
    # HandDevices sent no current TPDO: the first sample completes with the right drive's current
    assert events == [None] * 6 + [snapshots.WHEEL_SAMPLE, None]
    js = core.joint_state(t)
    drive = drivetrain(load_krang())
    efforts = dict(zip(js.names, js.efforts))
    nm_per_a = drive.torque_constant * drive.gear_ratio
    for joint, a in amps.items():
        assert efforts[joint] == pytest.approx(a * nm_per_a, rel=2e-3)
    assert all(math.isnan(efforts[j.joint]) for j in CFG.powercube.joints)
    assert len(js.efforts) == len(js.names)


def test_watchdog_sends_only_while_commands_stop():
    """Commands send their own frames; the watchdog timer never repeats a command in force (in
    lockstep simulation a repeat would pass for the controller's answer to the next sample), and
    once commands stop it sends zero current within WATCHDOG_QUIET_PERIODS refresh periods of
    the command going stale, again every such period."""
    core, dev, t = healthy_core()
    period = 1.0 / CFG.wheels.command_rate_hz
    timeout = CFG.wheels.command_timeout_s
    core.set_wheel_effort_command([10.0, 10.0], t)
    assert [wheel_amps_by_hand(f) for f in core.wheel_command_frames(t)] != [0.0, 0.0]

    def tick(now):  # the devices keep talking: only the command's age changes
        dev.feed(now)
        assert core.motion_allowed(now)
        return [wheel_amps_by_hand(f) for f in core.wheel_watchdog_frames(now)]

    quiet_ticks = np.arange(t + 0.5 * period, t + timeout, 0.5 * period)
    assert len(quiet_ticks) > 2 * commands.WATCHDOG_QUIET_PERIODS
    assert [tick(now) for now in quiet_ticks] == [[]] * len(quiet_ticks)
    late = t + timeout + period
    assert tick(late) == [0.0, 0.0]
    assert tick(late + 0.5 * period) == []
    assert tick(late + commands.WATCHDOG_QUIET_PERIODS * period) == [0.0, 0.0]
    # the loop counts as running either way: the drives' watchdog keeps being fed
    assert core.watchdog_frames(late) != []


def dmu_sample(core, t, seq, wobble=0):
    """One DMU sample at rest (-0.9 rad), its x rate `wobble` LSB off: what on_frame returned for
    the rates frame and for the accelerations frame."""
    m, g_lsb = CFG.imu.mount_angle_rad, 9.80665 * 0.0003
    f = (9.81 * math.sin(-0.9) * math.cos(m), -9.81 * math.sin(-0.9) * math.sin(m))
    f += (9.81 * math.cos(-0.9),)
    rates = [round(x / math.radians(0.008)) for x in CFG.imu.gyro_bias_rad_s]
    rates[0] += wobble
    accel = [round(x / g_lsb) for x in f]
    return (
        core.on_frame(msg(0x40, struct.pack('<hhhBB', *rates, 0, seq & 0xFF)), t, 'can3'),
        core.on_frame(msg(0x50, struct.pack('<hhhBB', *accel, 0, seq & 0xFF)), t, 'can3'),
    )


def test_a_dmu_whose_sequence_counter_is_stuck_is_silent_and_its_samples_dropped():
    core, dev, t = healthy_core()
    seq = dev.seq
    assert dmu_sample(core, t + 0.002, seq) == (None, snapshots.IMU_SAMPLE)
    for k in range(2, 40):  # the same frames again at the DMU's rate
        t_k = t + 0.002 * k
        assert dmu_sample(core, t_k, seq) == (None, None)
        dev.feed(t_k, imu=False)
        quiet = t_k - (t + 0.002)  # since the last live sample
        if abs(quiet - CFG.imu.silence_timeout_s) > 1e-6:
            assert core.motion_allowed(t_k) == (quiet < CFG.imu.silence_timeout_s), k
    assert core.imu_state(t_k) is None
    assert 'sequence counter stuck' in core.imu_frozen
    reports = {r.name: r for r in core.diagnostics(t_k)}
    assert reports['can_bridge: imu'].level == snapshots.ERROR
    assert 'frozen' in reports['can_bridge: motion'].message
    assert core.counters.frozen_samples == 38
    # live again: the counter advances
    assert dmu_sample(core, t_k + 0.002, seq + 1) == (None, snapshots.IMU_SAMPLE)
    dev.feed(t_k + 0.002, imu=False)
    assert core.motion_allowed(t_k + 0.002) and not core.imu_frozen


def test_dmu_values_repeated_longer_than_frozen_after_s_are_frozen():
    cfg = dataclasses.replace(CFG, imu=dataclasses.replace(CFG.imu, frozen_after_s=0.02))
    core = BridgeCore(cfg, clock=lambda: 0.0)
    dev = HandDevices(core)
    t, seq = 0.0, 0
    for k in range(cfg.imu.kalman.init_samples + 20):  # a noisy DMU: its x rate wobbles
        t += 0.002
        seq += 1
        dmu_sample(core, t, seq, wobble=k % 3)
        dev.feed(t, imu=False)
    assert core.motion_allowed(t)
    first = t + 0.002  # a new value, then the same again and again, the counter advancing
    done = []
    for _ in range(40):
        t += 0.002
        seq += 1
        done.append(dmu_sample(core, t, seq, wobble=(k + 1) % 3)[1])
        dev.feed(t, imu=False)
        if abs(t - first - cfg.imu.silence_timeout_s) > 1e-6:
            assert core.motion_allowed(t) == (t - first < cfg.imu.silence_timeout_s), t - first
    # published while a repeat is within the noise's allowance (frozen_after_s), dropped after
    kept = done.index(None)
    assert set(done[:kept]) == {snapshots.IMU_SAMPLE} and set(done[kept:]) == {None}
    assert kept - 1 == pytest.approx(cfg.imu.frozen_after_s / 0.002, abs=1)
    assert 'bit-identical' in core.imu_frozen
    # the sequence counter alone never freezes a live DMU with frozen_after_s 0 (the default)
    assert CFG.imu.frozen_after_s == 0.0


def test_startup_reads_the_watchdog_back_before_it_enables_the_drive():
    wd = CFG.wheels.watchdog
    steps = amc_canopen.startup_sequence(CFG.wheels.drive('JLWheel'), CFG.wheels)
    keys = [(s.action, s.index, s.subindex, s.value) for s in steps]
    verified = [s.action for s in steps].index('verified')
    consumer = (wd.node_id << 16) | round(wd.timeout_s * 1000)
    assert ('check', 0x1016, 1, consumer) in keys[:verified]
    assert ('check', 0x6007, 0, wd.abort_connection_option) in keys[:verified]
    assert verified < keys.index(('nmt', 0, 0, 0x01))  # before the NMT start and the enable
    # the consumer watches from its first beat: none is enabled before a beat went out
    armed = [s.action for s in steps].index('armed')
    assert verified < armed < min(i for i, k in enumerate(keys) if k[1] == 0x6040)


def test_a_drive_whose_watchdog_does_not_take_is_never_enabled():
    """A drive that forgets its heartbeat consumer (reads back 0): the start-up reports it and
    leaves the drive pre-operational, never enabled."""
    drive = CFG.wheels.drive('JLWheel')
    channel = f'startup-{uuid.uuid4().hex}'
    host, device = canopen.Network(), canopen.Network()
    host.connect(interface='virtual', channel=channel)
    device.connect(interface='virtual', channel=channel)
    node = canopen.LocalNode(drive.node_id, amc_canopen.object_dictionary(drive))
    node.add_read_callback(lambda index, subindex, od: 0 if index == 0x1016 else None)
    controlwords = []
    node.add_write_callback(
        lambda index, subindex, od, data: index == 0x6040 and controlwords.append(data)
    )
    device.add_node(node)
    try:
        mismatches = amc_canopen.run_startup(host, drive, CFG.wheels)
        assert len(mismatches) == 1 and 'heartbeat consumer' in mismatches[0], mismatches
        assert node.nmt.state != 'OPERATIONAL'
        assert controlwords == []  # no fault reset, no enable
    finally:
        host.disconnect()
        device.disconnect()
