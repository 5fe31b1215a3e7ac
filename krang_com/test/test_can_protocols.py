"""Codecs against frames built by hand from docs/can.md and the Krang drivers: ids, scales, signs,
byte order."""

import math
import struct

import can
import cantools
import pytest

from krang_can_bridge.config import ConfigError, load_devices
from krang_can_bridge.protocols import MalformedFrame, UnknownFrame, ValueOutOfRange, load_dbc
from krang_can_bridge.protocols import amc, amc_canopen, powercube as pc
from krang_can_bridge.protocols.dmu_imu import DmuAccelerations, DmuCodec, DmuRates
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

G = 9.80665


def msg(aid, data, **kw):
    return can.Message(arbitration_id=aid, data=bytes(data), is_extended_id=False, **kw)


@pytest.fixture(scope='module')
def cfg():
    return load_devices()


@pytest.fixture(scope='module')
def dbc(cfg):
    return load_dbc(cfg.dbc_path)


@pytest.fixture(scope='module')
def left(cfg, dbc):
    return amc.AmcDriveCodec(cfg.wheels.drive('JLWheel'), cfg.wheels, dbc)


@pytest.fixture(scope='module')
def right(cfg, dbc):
    return amc.AmcDriveCodec(cfg.wheels.drive('JRWheel'), cfg.wheels, dbc)


# ----------------------------------------------------------------------------------------------
# config
def test_config_matches_facts(cfg):
    assert [d.node_id for d in cfg.wheels.drives] == [0x20, 0x21]
    assert cfg.wheels.drive('JRWheel').sign == -1 and cfg.wheels.drive('JLWheel').sign == 1
    assert cfg.wheels.drivetrain == drivetrain(load_krang())  # the one drive-train description
    assert cfg.wheels.drivetrain.current_limit == 49.0
    assert cfg.wheels.encoder_counts_per_rev == 4000 and cfg.wheels.drivetrain.gear_ratio == 15
    # BLY343D, 12 oz-in/A as robot.yaml rounds it
    assert cfg.wheels.drivetrain.torque_constant == 0.0847
    assert set(cfg.joint_names) == {
        'JWaist',
        'JTorso',
        'LJ1',
        'LJ2',
        'LJ3',
        'LJ4',
        'LJ5',
        'LJ6',
        'LJFT',
        'RJ1',
        'RJ2',
        'RJ3',
        'RJ4',
        'RJ5',
        'RJ6',
        'RJFT',
        'JLWheel',
        'JRWheel',
    }
    waist = cfg.powercube.joint('JWaist')
    assert (waist.lower, waist.upper) == (0.0, 2.88)
    assert [m.sign for m in waist.modules] == [1, -1]
    # the sign-inverted module limits
    assert waist.module_limits(waist.modules[1]) == (-2.88, -0.0)
    assert cfg.powercube.joint('JTorso').lower == -1.57
    assert cfg.powercube.joint('LJ2').upper == 2.0944
    assert cfg.powercube.joint('LJ1').upper == pytest.approx(math.pi)
    assert cfg.powercube.joint('LJFT').max_velocity_rad_s == pytest.approx(math.radians(50))
    assert cfg.powercube.joint('LJ3').max_acceleration_rad_s2 == pytest.approx(math.radians(95))
    assert cfg.imu.mount_angle_rad == pytest.approx(-math.pi / 4)
    assert cfg.buses['can3'].bus_kwargs()['interface'] == 'udp_multicast'
    channels = [b.channel for b in cfg.buses.values()]
    assert len(set(channels)) == len(channels)


def test_robot_config_only_changes_buses(cfg):
    robot = load_devices(cfg.path.parent / 'can_devices_robot.yaml')
    assert robot.buses['can3'].interface == 'socketcan' and robot.buses['can11'].channel == 'can11'
    assert robot.wheels == cfg.wheels and robot.powercube == cfg.powercube


def test_config_rejects_bad_values(tmp_path, cfg):
    text = cfg.path.read_text().replace('sign: -1, peak_current_kp', 'sign: 2, peak_current_kp')
    (tmp_path / 'krang_can.dbc').write_text(cfg.dbc_path.read_text())
    bad = tmp_path / 'bad.yaml'
    bad.write_text(text)
    with pytest.raises(ConfigError):
        load_devices(bad)
    bad.write_text(cfg.path.read_text().replace('{bus: can0, id: 5,', '{bus: can0, id: 4,'))
    with pytest.raises(ConfigError):
        load_devices(bad)


def _with_wheel_keys(cfg, tmp_path, name, keys):
    """A copy of the device map whose `wheels` section also states `keys` (drive-train values)."""
    extra = ''.join(f'\n  {k}: {v}' for k, v in keys.items())
    text = cfg.path.read_text().replace('\nwheels:', '\nwheels:' + extra, 1)
    assert text != cfg.path.read_text()
    (tmp_path / 'krang_can.dbc').write_text(cfg.dbc_path.read_text())
    path = tmp_path / name
    path.write_text(text)
    return path


def test_device_map_with_a_disagreeing_torque_constant_is_rejected(tmp_path, cfg):
    """The 12 oz-in/A of the datasheet (0.0847386) is not the drive train's 0.0847: the drives
    would get 0.9995 of the current the controller computed, so the map is refused, naming file
    and key."""
    path = _with_wheel_keys(cfg, tmp_path, 'kt.yaml', {'torque_constant_nm_per_a': 0.0847386})
    with pytest.raises(ConfigError) as err:
        load_devices(path)
    text = str(err.value)
    assert str(path.resolve()) in text and 'wheels.torque_constant_nm_per_a' in text
    assert '0.0847386' in text and 'torque_constant = 0.0847' in text
    for key, value in (('gear_ratio', 14.0), ('current_limit_a', 50.0)):
        with pytest.raises(ConfigError, match=f'wheels.{key} = {value}'):
            load_devices(_with_wheel_keys(cfg, tmp_path, f'{key}.yaml', {key: value}))


def test_device_map_may_state_drive_train_values_that_agree(tmp_path, cfg):
    drive = cfg.wheels.drivetrain
    path = _with_wheel_keys(
        cfg,
        tmp_path,
        'agree.yaml',
        {
            'torque_constant_nm_per_a': drive.torque_constant,
            'gear_ratio': drive.gear_ratio,
            'current_limit_a': drive.current_limit,
        },
    )
    assert load_devices(path).wheels == cfg.wheels
    # the check names the file the `wheels` section came from, also through `extends`
    child = tmp_path / 'child.yaml'
    child.write_text('extends: kt.yaml\n')
    _with_wheel_keys(cfg, tmp_path, 'kt.yaml', {'torque_constant_nm_per_a': 0.0847386})
    with pytest.raises(ConfigError, match=str((tmp_path / 'kt.yaml').resolve())):
        load_devices(child)


# ----------------------------------------------------------------------------------------------
# AMC
def test_amc_cob_ids_follow_facts(left, right):
    # docs/can.md: 0x200 + 7*node + {0..6} -> 0x2E0-0x2E6 (node 0x20) and 0x2E7-0x2ED (node 0x21)
    assert [left.ids[k] for k in range(7)] == list(range(0x2E0, 0x2E7))
    assert [right.ids[k] for k in range(7)] == list(range(0x2E7, 0x2EE))


def test_amc_current_rpdo_bytes(cfg, left, right):
    kp = cfg.wheels.drive('JLWheel').peak_current_kp
    # DC2 = A * 2^15 / (Kp/10), truncated like the driver
    dc2 = int(10.0 * 2**15 / (kp / 10))
    m = left.encode_current_command(10.0)
    assert m.arbitration_id == 0x2E2 and bytes(m.data) == struct.pack('<Hh', 0x008F, dc2)
    assert bytes(m.data)[:2] == b'\x8f\x00'  # controlword 0x008F little-endian
    m = right.encode_current_command(10.0)  # right drive: current sign -1
    assert m.arbitration_id == 0x2E9 and bytes(m.data) == struct.pack('<Hh', 0x008F, -dc2)
    assert right.decode_current_command(m) == (0x008F, pytest.approx(dc2 * (kp / 10) / 2**15))


def test_amc_tpdo_decoding_by_hand(cfg, left, right):
    w, d = cfg.wheels, cfg.wheels.drive('JLWheel')
    one_wheel_rev = int(4000 * 15)
    r = left.decode(msg(0x2E3, struct.pack('<Hi', 0x0027, one_wheel_rev)))
    assert (r.joint, r.kind, r.statusword) == ('JLWheel', 'position', 0x27)
    assert r.value == pytest.approx(2 * math.pi)
    assert right.decode(
        msg(0x2EA, struct.pack('<Hi', 0x0027, one_wheel_rev))
    ).value == pytest.approx(-2 * math.pi)
    # DS1: counts/s = raw * k_i * k_s / 2^17
    raw = 2**17
    expected = (
        raw
        * d.k_i
        * d.k_s
        / 2**17
        * 2
        * math.pi
        / (w.encoder_counts_per_rev * w.drivetrain.gear_ratio)
    )
    assert left.decode(msg(0x2E4, struct.pack('<Hi', 0x27, raw))).value == pytest.approx(expected)
    assert right.decode(msg(0x2EB, struct.pack('<Hi', 0x27, raw))).value == pytest.approx(
        -expected
    )
    # DC1: amccan_decode_dc1 = raw / (2^13 / Kp) / 10  (the kit table omits the /10; the driver has
    # it)
    dc1_amps = 4096 / (2**13 / d.peak_current_kp) / 10
    assert left.decode(msg(0x2E5, struct.pack('<Hh', 0x27, 4096))).value == pytest.approx(dc1_amps)
    assert right.decode(msg(0x2EC, struct.pack('<Hh', 0x27, 4096))).value == pytest.approx(-30.0)
    s = left.decode(msg(0x2E6, struct.pack('<H', 0x0627)))
    assert (s.kind, s.value, s.statusword) == ('statusword', None, 0x0627)
    assert amc.drive_state(0x0627) == 'OPERATION_ENABLED'
    assert amc.drive_state(0x0040) == 'SWITCH_ON_DISABLED'
    assert amc.drive_state(0x0008) == 'FAULT'


def test_amc_round_trips(left, right):
    for codec in (left, right):
        assert codec.decode(codec.encode_position(1.2345, 0x27)).value == pytest.approx(
            1.2345, abs=2 * math.pi / 60000
        )
        assert codec.decode(codec.encode_velocity(-3.5, 0x27)).value == pytest.approx(
            -3.5, abs=1e-4
        )
        assert codec.decode(codec.encode_actual_current(-12.5, 0x27)).value == pytest.approx(
            -12.5, abs=0.01
        )
        cw, amps = codec.decode_current_command(codec.encode_current_command(-33.3))
        assert cw == 0x8F and abs(amps) <= 33.3 and amps == pytest.approx(-33.3, abs=0.002)


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf, 61.0, -1e9, 'x'])
def test_amc_encoder_rejects(left, bad):
    with pytest.raises(ValueOutOfRange):
        left.encode_current_command(bad)


def test_amc_malformed_frames_rejected(left):
    with pytest.raises(MalformedFrame):
        left.decode(msg(0x2E3, struct.pack('<Hi', 0, 0)[:5]))
    with pytest.raises(MalformedFrame):
        left.decode(msg(0x2E3, struct.pack('<Hi', 0, 0) + b'\x00'))
    with pytest.raises(MalformedFrame):
        left.decode(
            can.Message(arbitration_id=0x2E3, is_remote_frame=True, dlc=6, is_extended_id=False)
        )
    with pytest.raises(MalformedFrame):
        left.decode(can.Message(arbitration_id=0x2E3, data=bytes(6), is_extended_id=True))
    with pytest.raises(UnknownFrame):
        left.decode(msg(0x2EA, bytes(6)))  # the right drive's TPDO
    with pytest.raises(UnknownFrame):
        left.decode(msg(0x2E2, bytes(4)))  # an RPDO is not feedback


def test_amc_startup_sequence_enters_current_mode(cfg):
    steps = amc_canopen.startup_sequence(cfg.wheels.drive('JLWheel'), cfg.wheels)
    writes = [(s.index, s.subindex, s.value) for s in steps if s.action == 'write']
    assert (0x6060, 0, 4) in writes  # op-mode current
    # timer 1 (cycle in ms, then the TPDOs it drives) as the device map says, before the start
    timer = writes.index((0x2120, 0, cfg.wheels.tpdo_period_ms))
    assert writes[timer + 1] == (0x2121, 0, 0b1111)
    # RPDO current enabled at its COB-ID
    assert (0x1404, 1, 0x2E2) in writes
    assert (0x1402, 1, 0x2E0 | 1 << 31) in writes  # RPDO position disabled
    nmt = [s.value for s in steps if s.action == 'nmt']
    assert nmt == [0x80, 0x01]
    assert writes[-1] == (0x6040, 0, 0x0F) and writes.index((0x6060, 0, 4)) < len(writes) - 1


# ----------------------------------------------------------------------------------------------
# DMU
def test_dmu_frames_by_hand(dbc):
    codec = DmuCodec(dbc)
    r = codec.decode(msg(0x40, struct.pack('<hhhBB', 125, -250, 0, 7, 42)))
    assert isinstance(r, DmuRates) and (r.status, r.sequence) == (7, 42)
    # 0.008 deg/s per LSB
    assert (r.x, r.y, r.z) == pytest.approx((math.radians(1.0), math.radians(-2.0), 0.0))
    a = codec.decode(msg(0x50, struct.pack('<hhhBB', 1000, -3334, 32767, 0, 255)))
    assert isinstance(a, DmuAccelerations) and a.sequence == 255
    # 0.0003 g per LSB
    assert (a.x, a.y, a.z) == pytest.approx((0.3 * G, -3334 * 0.0003 * G, 32767 * 0.0003 * G))
    t = codec.stream_toggle()
    assert t.arbitration_id == 0x90 and bytes(t.data) == b'\x0f'
    assert codec.is_stream_toggle(t)


def test_dmu_encode_round_trip_and_rejects(dbc):
    codec = DmuCodec(dbc)
    m = codec.encode_rates((0.1, -0.2, 0.3), status=1, sequence=9)
    assert bytes(m.data) == struct.pack(
        '<hhhBB',
        round(0.1 / math.radians(0.008)),
        round(-0.2 / math.radians(0.008)),
        round(0.3 / math.radians(0.008)),
        1,
        9,
    )
    back = codec.decode(codec.encode_accelerations((0.0, -4.9, 9.81), sequence=3))
    assert (back.x, back.y, back.z) == pytest.approx((0.0, -4.9, 9.81), abs=0.0003 * G)
    # 5 rad/s > 32767 * 0.008 deg/s
    for bad in ((math.nan, 0, 0), (0, math.inf, 0), (5.0, 0, 0)):
        with pytest.raises(ValueOutOfRange):
            codec.encode_rates(bad)
    with pytest.raises(ValueOutOfRange):
        codec.encode_accelerations((0, 0, 100.0))  # > 9.83 g


def test_dmu_malformed_rejected(dbc):
    codec = DmuCodec(dbc)
    with pytest.raises(MalformedFrame):
        codec.decode(msg(0x40, bytes(7)))
    with pytest.raises(MalformedFrame):
        codec.decode(msg(0x50, bytes(9)))
    with pytest.raises(UnknownFrame):
        codec.decode(msg(0x41, bytes(8)))
    with pytest.raises(MalformedFrame):
        codec.is_stream_toggle(msg(0x90, b'\x01'))


# ----------------------------------------------------------------------------------------------
# DBC
def test_dbc_and_codecs_agree(cfg, dbc, left, right):
    """The file CAN engineers load decodes our frames to the same raw values and the scales of
    docs/can.md."""
    db = cantools.database.load_file(str(cfg.dbc_path))
    assert db.get_message_by_frame_id(0x40).get_signal_by_name('dQ_x').scale == 0.008
    assert db.get_message_by_frame_id(0x50).get_signal_by_name('acc_z').scale == 0.0003
    for codec in (left, right):
        m = codec.encode_current_command(-20.0)
        d = db.decode_message(m.arbitration_id, m.data, scaling=False)
        assert d['controlword'] == 0x8F
        assert d['target_current_dc2'] == struct.unpack('<Hh', bytes(m.data))[1]
        for offset, length in ((3, 6), (4, 6), (5, 4), (6, 2)):
            assert db.get_message_by_frame_id(codec.ids[offset]).length == length
    rates = DmuCodec(dbc).encode_rates((0.05, -0.01, 0.0), sequence=5)
    d = db.decode_message(0x40, rates.data)
    assert d['dQ_x'] == pytest.approx(math.degrees(0.05), abs=0.008)
    assert d['sequence'] == 5


# ----------------------------------------------------------------------------------------------
# PowerCube
def test_powercube_host_frames_by_hand():
    m = pc.get_param(4, pc.ACT_FPOS)
    assert m.arbitration_id == 0x0C4 and bytes(m.data) == bytes([0x0A, 0x3C])
    m = pc.set_motion(13, pc.FRAMP_ACK, 1.5)
    assert m.arbitration_id == 0x0ED and bytes(m.data) == bytes([0x0B, 14]) + struct.pack(
        '<f', 1.5
    )
    m = pc.set_param(5, pc.TARGET_VEL, 0.25)
    assert m.arbitration_id == 0x0E5 and bytes(m.data) == bytes([0x08, 0x4F]) + struct.pack(
        '<f', 0.25
    )
    m = pc.simple_command(7, pc.RESET)
    assert m.arbitration_id == 0x0E7 and bytes(m.data) == b'\x00'
    m = pc.broadcast_command(pc.HALT)
    assert m.arbitration_id == 0x100 and bytes(m.data) == b'\x02'
    assert pc.decode_request(pc.set_motion(9, pc.FVEL_ACK, -0.5)) == (9, 0x0B, 17, -0.5)
    assert pc.decode_request(pc.get_param(10, pc.ACT_FVEL)) == (10, 0x0A, 0x41, None)


def test_powercube_replies_by_hand():
    r = pc.decode_reply(msg(0x0A4, bytes([0x0A, 0x3C]) + struct.pack('<f', -0.25)))
    assert (r.module_id, r.command, r.selector, r.value) == (4, 0x0A, 0x3C, -0.25)
    r = pc.decode_reply(msg(0x0AD, bytes([0x0B, 14]) + struct.pack('<f', 0.75) + bytes([0x20, 0])))
    assert (r.module_id, r.command, r.selector, r.value, r.short_state) == (
        13,
        0x0B,
        14,
        0.75,
        0x20,
    )
    r = pc.decode_reply(msg(0x0A6, bytes([0x0A, 0x27]) + struct.pack('<I', 0x8002)))
    # state word stays an integer
    assert r.value == 0x8002
    assert pc.decode_reply(msg(0x0A7, b'\x00')) == (7, 0, None, None, None)
    assert pc.decode_reply(pc.reply_motion(8, 17, 1.25, 0x10)) == (8, 0x0B, 17, 1.25, 0x10)


def test_powercube_malformed_rejected():
    with pytest.raises(MalformedFrame):
        pc.decode_reply(msg(0x0A4, bytes([0x0A, 0x3C]) + struct.pack('<f', math.nan)))
    with pytest.raises(MalformedFrame):
        pc.decode_reply(msg(0x0A4, bytes([0x0A, 0x3C, 0, 0, 0])))  # DLC 5
    with pytest.raises(MalformedFrame):
        pc.decode_reply(msg(0x0A4, bytes([0x0B, 99]) + bytes(6)))  # unknown motion
    with pytest.raises(MalformedFrame):
        pc.decode_reply(msg(0x0A4, bytes([0x55]) + bytes(5)))  # unknown command
    with pytest.raises(UnknownFrame):
        pc.decode_reply(msg(0x0C4, bytes([0x0A, 0x3C])))  # a host frame
    for bad in (math.nan, math.inf, 1e39):
        with pytest.raises(ValueOutOfRange):
            pc.set_motion(4, pc.FRAMP_ACK, bad)
    with pytest.raises(ValueOutOfRange):
        pc.set_motion(4, 15, 0.0)
    with pytest.raises(ValueOutOfRange):
        pc.get_param(32, pc.ACT_FPOS)
