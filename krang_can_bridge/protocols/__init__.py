"""Krang's CAN device protocols: pure encode/decode on python-can `can.Message`, one module per
device family.

- `amc`: AMC wheel drives (CANopen DS402 PDOs, current mode; canopen for NMT/SDO start-up).
- `dmu_imu`: Silicon Sensing DMU IMU (raw frames 0x40 / 0x50 / 0x90).
- `powercube`: Schunk PowerCube modules (Amtec protocol).

Fixed-layout frames (IMU, AMC PDOs) are packed and unpacked with cantools from
config/krang_can.dbc, the file CAN engineers load into their own tools. Every decoder raises a
`ProtocolError` subclass on a frame it cannot trust, and every encoder refuses NaN, inf and
out-of-range values instead of wrapping them.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import can
import cantools


class ProtocolError(ValueError):
    """Base class: a frame or a value that must not be trusted or sent."""


class UnknownFrame(ProtocolError):
    """The arbitration id does not belong to this device or codec."""


class MalformedFrame(ProtocolError):
    """Known id, but wrong length, wrong command bytes, remote/error frame or a NaN payload."""


class ValueOutOfRange(ProtocolError):
    """A value to encode is NaN, infinite or does not fit the wire format."""


@functools.lru_cache(maxsize=8)
def _load_dbc_cached(path: str) -> cantools.database.can.Database:
    return cantools.database.load_file(path)


def load_dbc(path: str | Path) -> cantools.database.can.Database:
    """The DBC of the fixed-layout frames (cached per path: codecs share one parsed database)."""
    return _load_dbc_cached(str(Path(path).resolve()))


def require_finite(value: float, what: str) -> float:
    """Return `value` as float, or raise ValueOutOfRange for NaN/inf/non-numbers."""
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueOutOfRange(f'{what}: not a number ({value!r})') from exc
    if not math.isfinite(v):
        raise ValueOutOfRange(f'{what}: not finite ({v})')
    return v


def check_data_frame(msg: can.Message, expected_dlc: int | tuple[int, ...], what: str) -> None:
    """Reject remote/error/extended frames and frames whose DLC is not the expected one."""
    if msg.is_error_frame or msg.is_remote_frame:
        raise MalformedFrame(f'{what}: error or remote frame')
    if msg.is_extended_id:
        raise MalformedFrame(f'{what}: extended id 0x{msg.arbitration_id:X}')
    allowed = (expected_dlc,) if isinstance(expected_dlc, int) else expected_dlc
    if len(msg.data) not in allowed:
        raise MalformedFrame(
            f'{what}: DLC {len(msg.data)}, expected {"/".join(map(str, allowed))}'
        )


def frame(arbitration_id: int, data: bytes | bytearray) -> can.Message:
    """A standard-id data frame."""
    return can.Message(arbitration_id=arbitration_id, data=bytes(data), is_extended_id=False)


__all__ = [
    'ProtocolError',
    'UnknownFrame',
    'MalformedFrame',
    'ValueOutOfRange',
    'load_dbc',
    'require_finite',
    'check_data_frame',
    'frame',
]
