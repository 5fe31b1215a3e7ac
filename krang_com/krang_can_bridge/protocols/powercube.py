"""Schunk PowerCube modules (waist, torso, arms): Amtec's CAN protocol, not CANopen (docs/can.md).

Checked against the Krang driver (munzir/Krang-Software drivers/pcio/{pcio.c, include/pcio.h}),
which follows Amtec's "Data Exchange with PowerCube" rev 1.3:

- CAN ids: module -> host acknowledgements 0x0A0 + id, host "get" 0x0C0 + id, host "put" 0x0E0 +
  id, all modules 0x100; id = the module address (5 bits). The data kit lists only 0x0E0 + id for
  host -> module: the driver sends GET_PARAM on 0x0C0 + id (PCIO_IDMASK_CMDGET) and everything else
  on 0x0E0 + id, so do we.
- Frames: [cmd] for RESET/HOME/HALT; [cmd][param] for GET_PARAM; [cmd][param or motion][32-bit LE]
  for SET_PARAM/SET_MOTION. Floats are IEEE float32 little-endian (aa_endconv_st_le_u32 on the
  float bits).
- Replies: RESET/HOME/HALT -> [cmd] (1 byte, pcio_group_msg_recv matches `1 == msg.len`);
  GET_PARAM -> [0x0A][param][value LE] (6 bytes); SET_PARAM -> [0x08][param][status] (3 bytes);
  SET_MOTION with an _ACK motion -> [0x0B][motion][float32 actual position][short state][dio] (the
  driver reads the short state from byte 6; byte 7 is the digital I/O byte of the Amtec manual,
  sent as 0 by our emulator).
- Positions in rad, velocities in rad/s; FRAMP moves with the module's TARGET_VEL / TARGET_ACC
  parameters, which the host sets with SET_PARAM before the motion (pcio_group_setpos).
"""

from __future__ import annotations

import math
import struct
from typing import NamedTuple

import can

from krang_can_bridge.protocols import (
    MalformedFrame,
    UnknownFrame,
    ValueOutOfRange,
    check_data_frame,
    frame,
    require_finite,
)

ACK_BASE = 0x0A0
GET_BASE = 0x0C0
PUT_BASE = 0x0E0
BROADCAST_ID = 0x100
MODULE_ID_MASK = 0x1F

RESET, HOME, HALT, SET_PARAM, GET_PARAM, SET_MOTION = 0x00, 0x01, 0x02, 0x08, 0x0A, 0x0B
SIMPLE_COMMANDS = frozenset({RESET, HOME, HALT})

FRAMP_ACK, FVEL_ACK, FCUR_ACK = 14, 17, 18
MOTIONS = frozenset({FRAMP_ACK, FVEL_ACK, FCUR_ACK})

CUBE_STATE = 0x27  # PCIO_PARAM_ERROR: the 32-bit long state word
CONFIG = 0x39
ACT_FPOS = 0x3C
ACT_FVEL = 0x41
MIN_FPOS = 0x45
MAX_FPOS = 0x46
MAX_VEL = 0x48
MAX_ACC = 0x4A
ACT_FPSEUDOCURRENT = 0x4D
TARGET_VEL = 0x4F
TARGET_ACC = 0x50
FLOAT_PARAMS = frozenset(
    {
        ACT_FPOS,
        ACT_FVEL,
        MIN_FPOS,
        MAX_FPOS,
        MAX_VEL,
        MAX_ACC,
        ACT_FPSEUDOCURRENT,
        TARGET_VEL,
        TARGET_ACC,
    }
)
U32_PARAMS = frozenset({CUBE_STATE, CONFIG})

# Long state word bits (pcio_state_t)
STATE_ERROR = 0x1
STATE_HOME_OK = 0x2
STATE_HALTED = 0x4
STATE_MOTION = 0x800
STATE_RAMP_END = 0x8000
# Short state byte bits (pcio_short_state_id)
SHORT_NOT_OK = 0x01  # error, or not homed, or halted
SHORT_MOTION = 0x10
SHORT_RAMP_END = 0x20

FLOAT32_MAX = 3.4028234663852886e38


class PowerCubeRequest(NamedTuple):
    """A host -> module frame. `module_id` is None for a broadcast; `value` is float/int or
    None."""

    module_id: int | None
    command: int
    selector: int | None  # parameter id (SET/GET_PARAM) or motion id (SET_MOTION)
    value: float | int | None


class PowerCubeReply(NamedTuple):
    """A module -> host frame. `value`: parameter value or actual position (SET_MOTION);
    `short_state` or None."""

    module_id: int
    command: int
    selector: int | None
    value: float | int | None
    short_state: int | None


def _f32(value: float, what: str) -> bytes:
    v = require_finite(value, what)
    if abs(v) > FLOAT32_MAX:
        raise ValueOutOfRange(f'{what}: {v} does not fit float32')
    return struct.pack('<f', v)


def _module_id(module_id: int) -> int:
    if not 0 < int(module_id) <= MODULE_ID_MASK:
        raise ValueOutOfRange(f'module id {module_id} outside 1..31')
    return int(module_id)


def _decode_value(selector: int, raw: bytes, what: str) -> float | int:
    if selector in FLOAT_PARAMS:
        (v,) = struct.unpack('<f', raw)
        if not math.isfinite(v):
            raise MalformedFrame(f'{what}: non-finite float {v}')
        return v
    (u,) = struct.unpack('<I', raw)
    return u


# ---- host -> module -----------------------------------------------------------------------------
def simple_command(module_id: int, command: int) -> can.Message:
    """RESET / HOME / HALT to one module."""
    if command not in SIMPLE_COMMANDS:
        raise ValueOutOfRange(f'0x{command:02X} is not RESET/HOME/HALT')
    return frame(PUT_BASE + _module_id(module_id), bytes([command]))


def broadcast_command(command: int) -> can.Message:
    if command not in SIMPLE_COMMANDS:
        raise ValueOutOfRange(f'0x{command:02X} is not RESET/HOME/HALT')
    return frame(BROADCAST_ID, bytes([command]))


def get_param(module_id: int, param: int) -> can.Message:
    return frame(GET_BASE + _module_id(module_id), bytes([GET_PARAM, param & 0xFF]))


def set_param(module_id: int, param: int, value: float | int) -> can.Message:
    """SET_PARAM; float32 for the float parameters, u32 otherwise."""
    if param in FLOAT_PARAMS:
        payload = _f32(value, f'param 0x{param:02X}')
    else:
        if not isinstance(value, int) or not 0 <= value <= 0xFFFFFFFF:
            raise ValueOutOfRange(f'param 0x{param:02X}: {value!r} is not a u32')
        payload = struct.pack('<I', value)
    return frame(PUT_BASE + _module_id(module_id), bytes([SET_PARAM, param]) + payload)


def set_motion(module_id: int, motion: int, value: float) -> can.Message:
    """SET_MOTION (FRAMP_ACK position [rad], FVEL_ACK velocity [rad/s], FCUR_ACK current [A])."""
    if motion not in MOTIONS:
        raise ValueOutOfRange(f'motion {motion} not one of {sorted(MOTIONS)}')
    return frame(
        PUT_BASE + _module_id(module_id),
        bytes([SET_MOTION, motion]) + _f32(value, f'motion {motion}'),
    )


def decode_request(msg: can.Message) -> PowerCubeRequest:
    """A host frame as a module sees it; UnknownFrame for ids outside 0x0C0-0x0FF / 0x100."""
    aid = msg.arbitration_id
    if aid == BROADCAST_ID:
        module_id = None
    elif GET_BASE <= aid <= PUT_BASE + MODULE_ID_MASK:
        module_id = aid & MODULE_ID_MASK
    else:
        raise UnknownFrame(f'0x{aid:03X} is not a PowerCube host frame')
    check_data_frame(msg, (1, 2, 6), 'PowerCube request')
    data = bytes(msg.data)
    cmd = data[0]
    if cmd in SIMPLE_COMMANDS and len(data) == 1:
        return PowerCubeRequest(module_id, cmd, None, None)
    if cmd == GET_PARAM and len(data) == 2:
        return PowerCubeRequest(module_id, cmd, data[1], None)
    if cmd == SET_PARAM and len(data) == 6:
        return PowerCubeRequest(
            module_id, cmd, data[1], _decode_value(data[1], data[2:6], 'SET_PARAM')
        )
    if cmd == SET_MOTION and len(data) == 6 and data[1] in MOTIONS:
        (v,) = struct.unpack('<f', data[2:6])
        if not math.isfinite(v):
            raise MalformedFrame(f'SET_MOTION {data[1]}: non-finite value')
        return PowerCubeRequest(module_id, cmd, data[1], v)
    raise MalformedFrame(f'PowerCube request {data.hex()} on 0x{aid:03X}')


# ---- module -> host -----------------------------------------------------------------------------
def reply_simple(module_id: int, command: int) -> can.Message:
    return frame(ACK_BASE + _module_id(module_id), bytes([command]))


def reply_get_param(module_id: int, param: int, value: float | int) -> can.Message:
    if param in FLOAT_PARAMS:
        payload = _f32(value, f'param 0x{param:02X}')
    else:
        payload = struct.pack('<I', int(value) & 0xFFFFFFFF)
    return frame(ACK_BASE + _module_id(module_id), bytes([GET_PARAM, param]) + payload)


def reply_set_param(module_id: int, param: int, status: int = 0) -> can.Message:
    return frame(ACK_BASE + _module_id(module_id), bytes([SET_PARAM, param, status & 0xFF]))


def reply_motion(
    module_id: int, motion: int, position: float, short_state: int, dio: int = 0
) -> can.Message:
    return frame(
        ACK_BASE + _module_id(module_id),
        bytes([SET_MOTION, motion])
        + _f32(position, 'position')
        + bytes([short_state & 0xFF, dio & 0xFF]),
    )


def decode_reply(msg: can.Message) -> PowerCubeReply:
    """A module acknowledgement (0x0A0 + id). MalformedFrame for wrong lengths, commands or NaN
    floats."""
    aid = msg.arbitration_id
    if not ACK_BASE < aid <= ACK_BASE + MODULE_ID_MASK:
        raise UnknownFrame(f'0x{aid:03X} is not a PowerCube reply')
    check_data_frame(msg, (1, 3, 6, 7, 8), 'PowerCube reply')
    module_id = aid & MODULE_ID_MASK
    data = bytes(msg.data)
    cmd = data[0]
    if cmd in SIMPLE_COMMANDS and len(data) == 1:
        return PowerCubeReply(module_id, cmd, None, None, None)
    if cmd == GET_PARAM and len(data) == 6:
        return PowerCubeReply(
            module_id, cmd, data[1], _decode_value(data[1], data[2:6], 'GET_PARAM reply'), None
        )
    if cmd == SET_PARAM and len(data) == 3:
        return PowerCubeReply(module_id, cmd, data[1], data[2], None)
    if cmd == SET_MOTION and len(data) in (7, 8) and data[1] in MOTIONS:
        (pos,) = struct.unpack('<f', data[2:6])
        if not math.isfinite(pos):
            raise MalformedFrame('SET_MOTION ack: non-finite position')
        return PowerCubeReply(module_id, cmd, data[1], pos, data[6])
    raise MalformedFrame(f'PowerCube reply {data.hex()} on 0x{aid:03X}')


def is_host_frame(arbitration_id: int) -> bool:
    """Ids a host sends (our own echoes on a shared bus)."""
    return (
        GET_BASE <= arbitration_id <= PUT_BASE + MODULE_ID_MASK or arbitration_id == BROADCAST_ID
    )
