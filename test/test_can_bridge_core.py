"""BridgeCore: clamping, NaN rejection, silence -> zero current, malformed frames counted, state
decoding.

Device traffic is built by hand with struct from docs/can.md (not with the codecs under test), and
every command frame the core produces is decoded by hand and checked against the limits of
config/can_devices.yaml.
"""
import math
import random
import struct

import can
import pytest

from krang_can_bridge.bridge import BridgeCore
from krang_can_bridge.config import load_devices
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

CFG = load_devices()
ADVERSARIAL = [math.nan, math.inf, -math.inf, 1e308, -1e308, 1e6, -1e6, 0.0, -0.0, 5e-324, 'nan',
               None, '12']


def msg(aid, data):
    return can.Message(arbitration_id=aid, data=bytes(data), is_extended_id=False)


class HandDevices:
    """Hand-built device frames: the AMC TPDOs, DMU samples and PowerCube replies of a healthy
    robot."""

    def __init__(self, core, pitch=-0.9):
        self.core, self.pitch, self.seq = core, pitch, 0
        self.module_pos = {(m.bus,
                            m.module_id): 0.0 for j in CFG.powercube.joints for m in j.modules}

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
            f = (9.81 * math.sin(self.pitch) * math.cos(m),
                 -9.81 * math.sin(self.pitch) * math.sin(m),
                 9.81 * math.cos(self.pitch))
            b = CFG.imu.gyro_bias_rad_s
            rates = [round(x / math.radians(0.008)) for x in b]
            c.on_frame(msg(0x40, struct.pack('<hhhBB', *rates, 0, self.seq)), t, 'can3')
            c.on_frame(msg(0x50, struct.pack('<hhhBB', *[round(x / g_lsb) for x in f], 0,
                                             self.seq)), t, 'can3')
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


def wheel_amps_by_hand(frame):
    """Physical current at the joint from an RPDO frame, decoded by hand (DC2, sign from the node
    id)."""
    assert frame.msg.arbitration_id in (0x2E2, 0x2E9) and frame.bus == 'can3'
    cw, dc2 = struct.unpack('<Hh', bytes(frame.msg.data))
    assert cw == 0x008F and len(frame.msg.data) == 4
    drive = CFG.wheels.drive('JLWheel' if frame.msg.arbitration_id == 0x2E2 else 'JRWheel')
    return drive.sign * dc2 * (drive.peak_current_kp / 10) / 2 ** 15


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
    lsb = 60.0 / 2 ** 15
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
        for f, effort in zip(frames, (left, right)):
            amps = wheel_amps_by_hand(f)
            assert abs(amps) <= limit
            try:
                e = float(effort)
            except (TypeError, ValueError):
                e = math.nan
            if not math.isfinite(e):
                assert amps == 0.0                                   # rejected -> zero current
            elif abs(e) > 100:
                assert abs(amps) == pytest.approx(limit, abs=60.0 / 2 ** 15)
    assert core.counters.rejected_commands > 0 and core.counters.clamped_commands > 0


def test_joint_commands_stay_inside_limits():
    core, _, t = healthy_core()
    rng = random.Random(2)
    names = CFG.body_joint_names
    for _ in range(200):
        targets = {n: rng.choice([rng.uniform(-20, 20),
                                  rng.choice(ADVERSARIAL)]) for n in rng.sample(names, 6)}
        targets['JLWheel'] = 1.0                                        # not a body joint: ignored
        check_joint_frames_within_limits(core.joint_position_frames(targets, t))
    frames = core.joint_position_frames({'JWaist': 1.5, 'LJ2': math.nan, 'JTorso': 99.0}, t)
    targets = check_joint_frames_within_limits(frames)
    assert ('JWaist', 1, pytest.approx(1.5)) in targets and ('JWaist', -1,
                                                             pytest.approx(-1.5)) in targets
    assert ('JTorso', 1, pytest.approx(1.57)) in targets
    assert not any(j == 'LJ2' for j, _, _ in targets)                   # NaN -> no motion
    assert 'LJ2' in core.counters.last_rejection or core.counters.rejected_commands >= 1
    edge = check_joint_frames_within_limits(core.joint_position_frames({'JWaist': 2.88,
                                                                        'LJ1': -math.pi}, t))
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
    assert [wheel_amps_by_hand(f) for f in core.wheel_current_frames(30.0, 30.0, 0.0)] == [0.0,
                                                                                           0.0]


def test_stale_effort_command_becomes_zero():
    core, dev, t = healthy_core()
    core.set_wheel_effort_command(10.0, 10.0, t)
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
    for _ in range(2000):                                                        # fuzz
        data = bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 8)))
        core.on_frame(msg(rng.choice([0x40, 0x50, 0x2E3, 0x2E4, 0x2E5, 0x2E6, 0x0A4, 0x0AD,
                                      rng.randrange(0x800)]),
                          data), t, rng.choice(['can0', 'can3', 'can11', 'nonexistent']))
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


def test_imu_state_and_stream_toggle():
    core, dev, t = healthy_core()
    imu = core.imu_state()
    assert (
        imu.ready
        and imu.pitch == pytest.approx(-0.9, abs=2e-3)
        and imu.pitch_rate == pytest.approx(0, abs=0.01)
    )
    assert core.imu_stream_frames(t) == []                     # streaming: never toggle
    retry = CFG.imu.stream_toggle_retry_s
    frames = core.imu_stream_frames(t + retry + 0.01)
    assert [(f.bus, f.msg.arbitration_id, bytes(f.msg.data)) for f in frames] == [('can3', 0x90,
                                                                                   b'\x0f')]
    assert core.imu_stream_frames(t + retry + 0.02) == []      # no toggle storm
    assert len(core.imu_stream_frames(t + 2 * retry + 0.03)) == 1


def test_inhibit_blocks_motion_and_is_reported():
    core, _, t = healthy_core()
    core.inhibit('startup/JLWheel', 'constants mismatch')
    assert not core.motion_allowed(t)
    assert [wheel_amps_by_hand(f) for f in core.wheel_current_frames(10.0, 10.0, t)] == [0.0, 0.0]
    assert 'constants mismatch' in core.diagnostics(t)[0].message
    core.inhibit('startup/JLWheel', None)
    assert core.motion_allowed(t)
