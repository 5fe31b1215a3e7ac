"""Krang's CAN device protocols: pure encode/decode on python-can `can.Message`, one module per
device family.

- `amc`: AMC wheel drives (CANopen DS402 PDOs, current mode; canopen for NMT/SDO start-up).
- `dmu_imu`: Silicon Sensing DMU IMU (raw frames 0x40 / 0x50 / 0x90).
- `powercube`: Schunk PowerCube modules (Amtec protocol).

Fixed-layout frames (IMU, AMC PDOs) are described by config/krang_can.dbc, the file CAN engineers
load into their own tools; cantools reads it, and the frames of every sample are packed and
unpacked by structs compiled from it (`FrameLayout`). Every decoder raises a
`ProtocolError` subclass on a frame it cannot trust, and every encoder refuses NaN, inf and
out-of-range values instead of wrapping them.
"""

from __future__ import annotations

import functools
import math
import struct
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


_STRUCT_CODES = {
    (8, False): 'B',
    (8, True): 'b',
    (16, False): 'H',
    (16, True): 'h',
    (32, False): 'I',
    (32, True): 'i',
}


class FrameLayout:
    """One fixed-layout DBC message as a precompiled struct, for the frames of every sample:
    cantools' generic encode and decode cost 2-30 us a frame here, struct under 1 us. The DBC
    stays the one description: the layout, names and raw ranges are read from it, and a message
    struct cannot express (not byte-aligned little-endian integers tiling the frame from bit 0)
    is refused. Raw values, as cantools' scaling=False; encode is strict like cantools'."""

    def __init__(self, message):
        self.name, self.length = message.name, message.length
        fmt, pos, ranges = '<', 0, []
        for sig in sorted(message.signals, key=lambda x: x.start):
            code = _STRUCT_CODES.get((sig.length, bool(sig.is_signed)))
            if sig.byte_order != 'little_endian' or sig.start != pos or code is None:
                raise UnknownFrame(f'DBC {message.name}: {sig.name} is not a byte-aligned int')
            lo = -(1 << (sig.length - 1)) if sig.is_signed else 0
            hi = (1 << (sig.length - 1)) - 1 if sig.is_signed else (1 << sig.length) - 1
            if sig.minimum is not None:
                lo = max(lo, math.ceil((sig.minimum - sig.offset) / sig.scale - 1e-9))
            if sig.maximum is not None:
                hi = min(hi, math.floor((sig.maximum - sig.offset) / sig.scale + 1e-9))
            fmt += code
            ranges.append((sig.name, lo, hi))
            pos += sig.length
        if pos != 8 * message.length:
            raise UnknownFrame(f'DBC {message.name}: signals do not fill its {message.length} B')
        self._struct = struct.Struct(fmt)
        self._ranges = tuple(ranges)
        self.names = tuple(name for name, _, _ in ranges)

    def encode(self, values: dict) -> bytes:
        """Raw signal values by name -> payload; ValueOutOfRange for a missing or out-of-range
        value."""
        raw = []
        for name, lo, hi in self._ranges:
            try:
                v = int(values[name])
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueOutOfRange(f'{self.name}: {name}: {exc!r}') from exc
            if not lo <= v <= hi:
                raise ValueOutOfRange(f'{self.name}: {name} = {v} outside [{lo}, {hi}]')
            raw.append(v)
        return self._struct.pack(*raw)

    def decode(self, data: bytes) -> dict:
        """Payload of exactly `length` bytes -> raw signal values by name."""
        return dict(zip(self.names, self._struct.unpack(data)))


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
    'FrameLayout',
]
