"""Silicon Sensing DMU IMU: raw CAN frames 0x40 (angular rates), 0x50 (accelerations),
0x90 (stream toggle).

Checked against the Krang driver (munzir/Krang-Software drivers/imu/ssdmu.c,
include/ssdmu/ssdmu.h):

- 0x40, 8 bytes: int16 dQ (rate about x), int16 dP (about y), int16 dR (about z), u8 status, u8
  sequence.
- 0x50, 8 bytes: int16 x, y, z acceleration, u8 status, u8 sequence.
- Byte order: the driver memcpy()s the payload into a packed struct of `short` on an x86 host, so
  the fields are little-endian. That is the only evidence available (no DMU datasheet at hand); the
  DBC says the same.
- Scales (ssdmu.c): 0.008 deg/s per LSB and 0.0003 g per LSB. They are read from
  config/krang_can.dbc, so the DBC is their single source; this module only converts deg -> rad and
  g -> m/s^2.
- A rates frame and an accelerations frame with the same sequence number form one sample.
- 0x90 [0x0F] *toggles* streaming (ssdmu_toggle_streaming): the host sends it only while the DMU is
  silent.
- Gyro biases are not removed here (imud published raw samples); the bridge subtracts the
  configured biases.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import can

from krang_can_bridge.protocols import (
    FrameLayout,
    MalformedFrame,
    UnknownFrame,
    ValueOutOfRange,
    check_data_frame,
    frame,
    require_finite,
)

RATES_ID = 0x40
ACCELERATIONS_ID = 0x50
STREAM_TOGGLE_ID = 0x90
STREAM_TOGGLE_COMMAND = 0x0F
STANDARD_GRAVITY = 9.80665  # m/s^2 per g (unit definition)
INT16_MIN, INT16_MAX = -(2**15), 2**15 - 1

_RATE_SIGNALS = ('dQ_x', 'dP_y', 'dR_z')
_ACCEL_SIGNALS = ('acc_x', 'acc_y', 'acc_z')


class DmuRates(NamedTuple):
    """Angular rates about the sensor x, y, z axes [rad/s], biases not removed."""

    x: float
    y: float
    z: float
    status: int
    sequence: int


class DmuAccelerations(NamedTuple):
    """Specific force along the sensor x, y, z axes [m/s^2] (+1 g along the axis pointing up at
    rest)."""

    x: float
    y: float
    z: float
    status: int
    sequence: int


class DmuCodec:
    """Encode/decode DMU frames with the layouts and LSB scales of the DBC."""

    def __init__(self, dbc):
        self._rates = dbc.get_message_by_frame_id(RATES_ID)
        self._accel = dbc.get_message_by_frame_id(ACCELERATIONS_ID)
        self._toggle = dbc.get_message_by_frame_id(STREAM_TOGGLE_ID)
        self._layouts = {m.frame_id: FrameLayout(m) for m in (self._rates, self._accel)}
        self.rate_lsb_rad_s = math.radians(self._scale(self._rates, _RATE_SIGNALS, 'deg/s'))
        self.accel_lsb_m_s2 = self._scale(self._accel, _ACCEL_SIGNALS, 'g') * STANDARD_GRAVITY

    @staticmethod
    def _scale(message, names: Sequence[str], unit: str) -> float:
        signals = {s.name: s for s in message.signals}
        scales = set()
        for n in names:
            s = signals.get(n)
            if s is None or s.unit != unit or s.length != 16 or not s.is_signed:
                raise UnknownFrame(f'DBC {message.name}: signal {n} must be int16 in {unit}')
            scales.add(s.scale)
        if len(scales) != 1:
            raise UnknownFrame(f'DBC {message.name}: axes have different scales {scales}')
        return scales.pop()

    feedback_ids = frozenset({RATES_ID, ACCELERATIONS_ID})
    command_ids = frozenset({STREAM_TOGGLE_ID})

    def decode(self, msg: can.Message) -> DmuRates | DmuAccelerations:
        if msg.arbitration_id == RATES_ID:
            message, names, lsb, cls = self._rates, _RATE_SIGNALS, self.rate_lsb_rad_s, DmuRates
        elif msg.arbitration_id == ACCELERATIONS_ID:
            message, names, lsb, cls = (
                self._accel,
                _ACCEL_SIGNALS,
                self.accel_lsb_m_s2,
                DmuAccelerations,
            )
        else:
            raise UnknownFrame(f'0x{msg.arbitration_id:03X} is not a DMU data frame')
        check_data_frame(msg, message.length, message.name)
        s = self._layouts[message.frame_id].decode(bytes(msg.data))
        return cls(*(s[n] * lsb for n in names), int(s['status']), int(s['sequence']))

    def _to_raw(self, values: Sequence[float], lsb: float, what: str) -> list[int]:
        if len(values) != 3:
            raise ValueOutOfRange(f'{what}: need 3 axes, got {len(values)}')
        raw = [round(require_finite(v, what) / lsb) for v in values]
        if any(not INT16_MIN <= r <= INT16_MAX for r in raw):
            raise ValueOutOfRange(
                f'{what}: {list(values)} outside the DMU range +-{INT16_MAX * lsb:.4g}'
            )
        return raw

    def rates_to_raw(self, rates_rad_s: Sequence[float]) -> list[int]:
        return self._to_raw(rates_rad_s, self.rate_lsb_rad_s, 'DMU rates')

    def accelerations_to_raw(self, accel_m_s2: Sequence[float]) -> list[int]:
        return self._to_raw(accel_m_s2, self.accel_lsb_m_s2, 'DMU accelerations')

    def _encode(
        self, message, names, raw: Sequence[int], status: int, sequence: int
    ) -> can.Message:
        values = dict(zip(names, (int(r) for r in raw)))
        values.update(status=int(status) & 0xFF, sequence=int(sequence) & 0xFF)
        return frame(message.frame_id, self._layouts[message.frame_id].encode(values))

    def encode_rates(
        self, rates_rad_s: Sequence[float], status: int = 0, sequence: int = 0
    ) -> can.Message:
        """0x40 from rates about sensor x, y, z [rad/s] (rounded to the LSB; raises beyond
        int16)."""
        return self._encode(
            self._rates, _RATE_SIGNALS, self.rates_to_raw(rates_rad_s), status, sequence
        )

    def encode_raw_rates(
        self, raw: Sequence[int], status: int = 0, sequence: int = 0
    ) -> can.Message:
        return self._encode(self._rates, _RATE_SIGNALS, raw, status, sequence)

    def encode_accelerations(
        self, accel_m_s2: Sequence[float], status: int = 0, sequence: int = 0
    ) -> can.Message:
        """0x50 from specific force along sensor x, y, z [m/s^2]."""
        return self._encode(
            self._accel, _ACCEL_SIGNALS, self.accelerations_to_raw(accel_m_s2), status, sequence
        )

    def encode_raw_accelerations(
        self, raw: Sequence[int], status: int = 0, sequence: int = 0
    ) -> can.Message:
        return self._encode(self._accel, _ACCEL_SIGNALS, raw, status, sequence)

    def stream_toggle(self) -> can.Message:
        """0x90 [0x0F]: toggles streaming on the DMU."""
        return frame(
            STREAM_TOGGLE_ID,
            self._toggle.encode({'command': STREAM_TOGGLE_COMMAND}, scaling=False),
        )

    def is_stream_toggle(self, msg: can.Message) -> bool:
        """True for a valid toggle command; raises MalformedFrame for a 0x90 frame with another
        payload."""
        if msg.arbitration_id != STREAM_TOGGLE_ID:
            return False
        check_data_frame(msg, self._toggle.length, self._toggle.name)
        if msg.data[0] != STREAM_TOGGLE_COMMAND:
            raise MalformedFrame(f'DMU command 0x{msg.data[0]:02X} is not the stream toggle')
        return True
