"""AMC wheel drives: CANopen DS402 objects with AMC's own PDOs, current mode (docs/can.md).

Wire format, checked against the Krang driver (munzir/Krang-Software
drivers/amc/{amccan,amcdrive,amciod}.c):

- COB-ID = 0x200 + 7*node + offset; offsets 0/1/2 = RPDO position/velocity/current (the host
  writes), 3/4/5/6 = TPDO position/velocity/current/statusword (the drive sends, async, driven by
  its timer 1, whose cycle in ms the host writes at start-up: the driver wrote 1000/update_freq,
  we write wheels.tpdo_period_ms).
- RPDO current (4 bytes): controlword 0x008F (u16 LE), target current DC2 (i16 LE), DC2 = A * 2^15
  / (Kp/10), truncated toward zero like the driver's int cast (so the current sent never exceeds
  the one asked for).
- TPDO position/velocity (6 bytes): 2 leading bytes, then i32 LE (counts; DS1 velocity units). The
  driver skips bytes 0-1 without naming them; we read them as the status word, which is how AMC
  maps its fixed TPDOs (our assumption - nothing in the driver depends on it).
- TPDO current (4 bytes): 2 leading bytes, then i16 LE in DC1 units, A = raw * (Kp/10) / 2^13. The
  data kit's table writes DC1 = raw/(2^13/Kp); amccan_decode_dc1 divides that by a further 10,
  consistent with Kp being in 0.1 A (amcdrive_set_current clamps at Kp/10 A). We follow the driver
  (docs/can.md).
- TPDO statusword (2 bytes): u16 LE.
- Velocity: counts/s = DS1 * k_i * k_s / 2^17 (amccan_decode_ds1).
- Position: rad = counts * 2 pi / (4000 * 15) at the wheel (amcdrive ticks_to_rad).
- The right drive (node 0x21) has current_sign -1, and ticks_to_rad applies it to position and
  velocity too.

The layouts live in config/krang_can.dbc and are packed with cantools; the scalings need per-drive
constants (Kp, k_i, k_s, counts/rev, gear), which live in config/can_devices.yaml, so the DBC
carries raw units.

The PDOs are plain frames here: AMC's COB-ID scheme and fixed mappings are not the CiA defaults
canopen's PDO classes would assume. What CANopen standardises and the Krang driver did by hand
(the object dictionary, NMT, the SDO start-up sequence) is in amc_canopen.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import can

from krang_can_bridge.config import WatchdogConfig, WheelDriveConfig, WheelsConfig
from krang_can_bridge.protocols import (
    FrameLayout,
    UnknownFrame,
    ValueOutOfRange,
    check_data_frame,
    frame,
    require_finite,
)

# COB-ID scheme chosen by the Krang driver (amcdrive_enable_pdos: cob_base 0x200, "What the heck is
# the 7 from?").
COB_BASE = 0x200
COB_STRIDE = 7
RPDO_POSITION, RPDO_VELOCITY, RPDO_CURRENT = 0, 1, 2
TPDO_POSITION, TPDO_VELOCITY, TPDO_CURRENT, TPDO_STATUSWORD = 3, 4, 5, 6

CONTROLWORD_CURRENT_PDO = 0x008F  # amcdrive_rpdo_cw_i32: enable operation + fault-reset bit
OP_MODE_CURRENT = 4

# DS402 objects
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_CURRENT = 0x6071
CURRENT_ACTUAL = 0x6078
HEARTBEAT_TIME = 0x1017
# Drive-side watchdog (DS301 0x100C/0x100D/0x1016, DS402 0x6007; docs/can.md)
GUARD_TIME = 0x100C
LIFE_TIME_FACTOR = 0x100D
CONSUMER_HEARTBEAT_TIME = 0x1016
ABORT_CONNECTION_OPTION = 0x6007
ABORT_NO_ACTION, ABORT_FAULT, ABORT_DISABLE_VOLTAGE, ABORT_QUICK_STOP = 0, 1, 2, 3
HEARTBEAT_BASE = 0x700
NMT_STATE_OPERATIONAL = 0x05  # the bridge's heartbeat payload
# AMC manufacturer objects (amccan.h)
BOARD_INFO = 0x20D8
BOARD_INFO_MAX_PEAK_CURRENT = 0x0C  # Kp, 0.1 A
BOARD_INFO_SWITCH_FREQ = 0x24  # PBF: kHz * 2^16
FEEDBACK_PARAMETERS = 0x2032
FEEDBACK_POS_INTERPOLATION = 0x08  # k_i
TIMER1_CYCLE = 0x2120
TIMER1_TPDOS = 0x2121
# PDO communication parameter objects of the AMC PDOs the driver uses (amccan.c pdo_com_index)
RPDO_COMM = {RPDO_POSITION: 0x1402, RPDO_VELOCITY: 0x1403, RPDO_CURRENT: 0x1404}
TPDO_COMM = {
    TPDO_STATUSWORD: 0x1800,
    TPDO_POSITION: 0x1802,
    TPDO_VELOCITY: 0x1803,
    TPDO_CURRENT: 0x1804,
}
# AMC's fixed mappings as the wire layouts imply them (the leading status word of TPDO 3/4/5 is our
# reading).
PDO_MAPPINGS = {
    RPDO_POSITION: ((CONTROLWORD, 0, 16), (0x607A, 0, 32)),
    RPDO_VELOCITY: ((CONTROLWORD, 0, 16), (0x60FF, 0, 32)),
    RPDO_CURRENT: ((CONTROLWORD, 0, 16), (TARGET_CURRENT, 0, 16)),
    TPDO_STATUSWORD: ((STATUSWORD, 0, 16),),
    TPDO_POSITION: ((STATUSWORD, 0, 16), (POSITION_ACTUAL, 0, 32)),
    TPDO_VELOCITY: ((STATUSWORD, 0, 16), (VELOCITY_ACTUAL, 0, 32)),
    TPDO_CURRENT: ((STATUSWORD, 0, 16), (CURRENT_ACTUAL, 0, 16)),
}
TIMER1_TPDO_BITS = 0b1111  # TPDO 1, 3, 4, 5 (bit i = i-th entry from AMCCAN_TPDO_1)
PDO_TRANS_ASYNC = 0xFE
PDO_COB_DISABLED = 1 << 31

# Controlword commands (amccan.h amccan_control_state_t)
CW_SHUTDOWN = 0x06
CW_SWITCH_ON = 0x07
CW_ENABLE_OPERATION = 0x0F
CW_RESET_FAULT = 0x80
CW_DISABLE_VOLTAGE = 0x00
CW_QUICK_STOP = 0x02

# Statusword -> state (amccan_decode_state: value, mask)
DRIVE_STATES = (
    ('NOT_READY', 0x00, 0x4F),
    ('SWITCH_ON_DISABLED', 0x40, 0x4F),
    ('READY_TO_SWITCH_ON', 0x21, 0x6F),
    ('SWITCHED_ON', 0x23, 0x6F),
    ('OPERATION_ENABLED', 0x27, 0x6F),
    ('FAULT', 0x08, 0x4F),
    ('QUICK_STOP_ACTIVE', 0x03, 0x6F),
)
STATUSWORD_OF_STATE = {name: value for name, value, _ in DRIVE_STATES}

NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_RESET_NODE, NMT_RESET_COMMUNICATION = (
    0x01,
    0x02,
    0x80,
    0x81,
    0x82,
)

DC2_FULL_SCALE = 2**15
DC1_FULL_SCALE = 2**13
DS1_FULL_SCALE = 2**17
INT16_MIN, INT16_MAX = -(2**15), 2**15 - 1
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1


def drive_state(statusword: int) -> str:
    """DS402 state name from a status word (amccan_decode_state order)."""
    for name, value, mask in DRIVE_STATES:
        if statusword & mask == value:
            return name
    return 'UNKNOWN'


def cob_id(node_id: int, offset: int) -> int:
    return COB_BASE + COB_STRIDE * node_id + offset


class AmcReading(NamedTuple):
    """One decoded TPDO: `kind` is position [rad], velocity [rad/s], current [A] or statusword
    (value None)."""

    joint: str
    kind: str
    value: float | None
    statusword: int


class AmcDriveCodec:
    """Encode/decode the PDOs of one drive, in physical units at the wheel joint (sign applied)."""

    def __init__(self, drive: WheelDriveConfig, wheels: WheelsConfig, dbc):
        self.drive = drive
        self.wheels = wheels
        self.ids = {k: cob_id(drive.node_id, k) for k in range(7)}
        self._kind_of_id = {
            self.ids[TPDO_POSITION]: 'position',
            self.ids[TPDO_VELOCITY]: 'velocity',
            self.ids[TPDO_CURRENT]: 'current',
            self.ids[TPDO_STATUSWORD]: 'statusword',
        }
        self._messages = {}
        self._layouts = {}  # the same messages as struct layouts (the per-sample frames)
        expected = {
            RPDO_CURRENT: {'controlword', 'target_current_dc2'},
            TPDO_POSITION: {'statusword', 'position_counts'},
            TPDO_VELOCITY: {'statusword', 'velocity_ds1'},
            TPDO_CURRENT: {'statusword', 'current_dc1'},
            TPDO_STATUSWORD: {'statusword'},
        }
        for offset, signals in expected.items():
            try:
                message = dbc.get_message_by_frame_id(self.ids[offset])
            except KeyError as exc:
                raise UnknownFrame(
                    f'DBC has no frame 0x{self.ids[offset]:03X} for AMC node 0x{drive.node_id:02X}'
                ) from exc
            if {s.name for s in message.signals} != signals:
                raise UnknownFrame(
                    f'DBC frame {message.name} has signals '
                    f'{[s.name for s in message.signals]}, expected '
                    f'{sorted(signals)}'
                )
            self._messages[offset] = message
            self._layouts[offset] = FrameLayout(message)
        self._amps_per_dc2 = drive.peak_current_a / DC2_FULL_SCALE
        self._amps_per_dc1 = drive.peak_current_a / DC1_FULL_SCALE
        self._counts_per_rad = wheels.counts_per_wheel_rad
        self._counts_per_s_per_ds1 = drive.k_i * drive.k_s / DS1_FULL_SCALE

    # ---- ids ------------------------------------------------------------------------------------
    @property
    def command_ids(self) -> frozenset[int]:
        """Ids the host sends to this drive (RPDOs)."""
        return frozenset(self.ids[k] for k in (RPDO_POSITION, RPDO_VELOCITY, RPDO_CURRENT))

    @property
    def feedback_ids(self) -> frozenset[int]:
        return frozenset(self._kind_of_id)

    def _pack(self, offset: int, signals: dict) -> can.Message:
        return frame(self.ids[offset], self._layouts[offset].encode(signals))

    def _unpack(self, offset: int, msg: can.Message) -> dict:
        layout = self._layouts[offset]
        check_data_frame(msg, layout.length, layout.name)
        return layout.decode(bytes(msg.data))

    # ---- host -> drive --------------------------------------------------------------------------
    def current_to_dc2(self, amps: float) -> int:
        """DC2 truncated toward zero, as amcdrive_set_current's int cast: the sent current never
        exceeds |amps|."""
        amps = require_finite(amps, f'{self.drive.joint} current')
        raw = math.trunc(self.drive.sign * amps / self._amps_per_dc2)
        if not INT16_MIN <= raw <= INT16_MAX:
            raise ValueOutOfRange(
                f'{self.drive.joint}: {amps} A exceeds the drive peak '
                f'{self.drive.peak_current_a} A'
            )
        return raw

    def encode_current_command(self, amps: float) -> can.Message:
        """RPDO current: [controlword 0x008F][DC2]. Raises ValueOutOfRange for NaN/inf or beyond
        the drive peak."""
        return self._pack(
            RPDO_CURRENT,
            {
                'controlword': CONTROLWORD_CURRENT_PDO,
                'target_current_dc2': self.current_to_dc2(amps),
            },
        )

    def decode_current_command(self, msg: can.Message) -> tuple[int, float]:
        """(controlword, amps at the joint) of an RPDO current frame (the drive's view)."""
        if msg.arbitration_id != self.ids[RPDO_CURRENT]:
            raise UnknownFrame(
                f'0x{msg.arbitration_id:03X} is not the current RPDO of {self.drive.joint}'
            )
        s = self._unpack(RPDO_CURRENT, msg)
        return int(s['controlword']), self.drive.sign * s[
            'target_current_dc2'
        ] * self._amps_per_dc2

    # ---- drive -> host --------------------------------------------------------------------------
    def decode(self, msg: can.Message) -> AmcReading:
        kind = self._kind_of_id.get(msg.arbitration_id)
        if kind is None:
            raise UnknownFrame(
                f'0x{msg.arbitration_id:03X} is not a TPDO of AMC node 0x{self.drive.node_id:02X}'
            )
        sign = self.drive.sign
        if kind == 'position':
            s = self._unpack(TPDO_POSITION, msg)
            value = sign * s['position_counts'] / self._counts_per_rad
        elif kind == 'velocity':
            s = self._unpack(TPDO_VELOCITY, msg)
            value = sign * s['velocity_ds1'] * self._counts_per_s_per_ds1 / self._counts_per_rad
        elif kind == 'current':
            s = self._unpack(TPDO_CURRENT, msg)
            value = sign * s['current_dc1'] * self._amps_per_dc1
        else:
            s = self._unpack(TPDO_STATUSWORD, msg)
            value = None
        return AmcReading(self.drive.joint, kind, value, int(s['statusword']))

    def position_counts(self, position_rad: float) -> int:
        return round(
            self.drive.sign * require_finite(position_rad, 'position') * self._counts_per_rad
        )

    def encode_position(self, position_rad: float, statusword: int) -> can.Message:
        counts = self.position_counts(position_rad)
        if not INT32_MIN <= counts <= INT32_MAX:
            raise ValueOutOfRange(
                f'{self.drive.joint}: position {position_rad} rad overflows int32 counts'
            )
        return self._pack(TPDO_POSITION, {'statusword': statusword, 'position_counts': counts})

    def encode_position_counts(self, counts: int, statusword: int) -> can.Message:
        return self._pack(
            TPDO_POSITION, {'statusword': statusword, 'position_counts': int(counts)}
        )

    def encode_velocity(self, velocity_rad_s: float, statusword: int) -> can.Message:
        v = require_finite(velocity_rad_s, 'velocity')
        raw = round(self.drive.sign * v * self._counts_per_rad / self._counts_per_s_per_ds1)
        return self._pack(TPDO_VELOCITY, {'statusword': statusword, 'velocity_ds1': raw})

    def encode_actual_current(self, amps: float, statusword: int) -> can.Message:
        raw = round(self.drive.sign * require_finite(amps, 'current') / self._amps_per_dc1)
        return self._pack(TPDO_CURRENT, {'statusword': statusword, 'current_dc1': raw})

    def encode_statusword(self, statusword: int) -> can.Message:
        return self._pack(TPDO_STATUSWORD, {'statusword': statusword})


def heartbeat_frame(watchdog: WatchdogConfig) -> can.Message:
    """The bridge's heartbeat (DS301: 0x700 + node id, one byte NMT state, here OPERATIONAL)."""
    return frame(HEARTBEAT_BASE + watchdog.node_id, bytes([NMT_STATE_OPERATIONAL]))


def guarding_request(node_id: int) -> can.Message:
    """A node-guarding request: a remote frame on 0x700 + the drive's node id (DS301)."""
    return can.Message(
        arbitration_id=HEARTBEAT_BASE + node_id, is_remote_frame=True, dlc=1, is_extended_id=False
    )


def codecs_from_config(wheels: WheelsConfig, dbc) -> dict[str, AmcDriveCodec]:
    """One codec per drive, keyed by joint name."""
    return {d.joint: AmcDriveCodec(d, wheels, dbc) for d in wheels.drives}
