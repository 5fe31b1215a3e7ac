"""AMC wheel drives over CANopen: the object dictionary of the objects we touch (the drive's
side in the simulator, canopen.LocalNode), the start-up sequence (NMT, fault reset, the watchdog
objects, the PDOs and their timer, enable) and `run_startup`, which runs it through SDO. The wire
codec of the PDOs is in amc."""

from __future__ import annotations

from dataclasses import dataclass

import canopen
from canopen import objectdictionary as od

from krang_can_bridge.config import WatchdogConfig, WheelDriveConfig, WheelsConfig
from krang_can_bridge.protocols.amc import (
    ABORT_CONNECTION_OPTION,
    ABORT_FAULT,
    BOARD_INFO,
    BOARD_INFO_MAX_PEAK_CURRENT,
    BOARD_INFO_SWITCH_FREQ,
    CONSUMER_HEARTBEAT_TIME,
    CONTROLWORD,
    CURRENT_ACTUAL,
    CW_ENABLE_OPERATION,
    CW_RESET_FAULT,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    FEEDBACK_PARAMETERS,
    FEEDBACK_POS_INTERPOLATION,
    GUARD_TIME,
    HEARTBEAT_TIME,
    LIFE_TIME_FACTOR,
    MODES_OF_OPERATION,
    MODES_OF_OPERATION_DISPLAY,
    NMT_PRE_OPERATIONAL,
    NMT_START,
    OP_MODE_CURRENT,
    PDO_COB_DISABLED,
    PDO_MAPPINGS,
    PDO_TRANS_ASYNC,
    POSITION_ACTUAL,
    RPDO_COMM,
    RPDO_CURRENT,
    STATUSWORD,
    STATUSWORD_OF_STATE,
    TARGET_CURRENT,
    TIMER1_CYCLE,
    TIMER1_TPDOS,
    TIMER1_TPDO_BITS,
    TPDO_COMM,
    VELOCITY_ACTUAL,
    cob_id,
)


@dataclass(frozen=True)
class StartupStep:
    """One step of the drive start-up: an NMT command, an SDO write, or an SDO read to compare with
    config."""

    action: str  # 'nmt' | 'write' | 'check' | 'verified' (stop here after any mismatch)
    index: int = 0
    subindex: int = 0
    value: int = 0  # NMT command, value written, or expected value
    what: str = ''


def _var(
    index: int,
    subindex: int,
    name: str,
    data_type: int,
    access: str = 'rw',
    default: int | None = None,
):
    v = od.ODVariable(name, index, subindex)
    v.data_type = data_type
    v.access_type = access
    if default is not None:
        v.default = default
    return v


def _record(index: int, name: str, subs: list) -> od.ODRecord:
    rec = od.ODRecord(name, index)
    rec.add_member(
        _var(index, 0, 'highest sub-index', od.UNSIGNED8, 'ro', max(s.subindex for s in subs))
    )
    for s in subs:
        rec.add_member(s)
    return rec


def switching_frequency_pbf(k_s_hz: float) -> int:
    """Inverse of amcccan_decode_pbf: the drive reports kHz in 16.16 fixed point (k_s = 1000 * pbf
    / 2^16)."""
    return round(k_s_hz / 1000.0 * (1 << 16))


def object_dictionary(drive: WheelDriveConfig) -> od.ObjectDictionary:
    """The DS402/AMC objects the bridge and the emulator use, with this drive's constants as
    defaults."""
    d = od.ObjectDictionary()
    d.node_id = drive.node_id
    d.add_object(_var(HEARTBEAT_TIME, 0, 'Producer heartbeat time', od.UNSIGNED16, 'rw', 0))
    d.add_object(_var(GUARD_TIME, 0, 'Guard time', od.UNSIGNED16, 'rw', 0))
    d.add_object(_var(LIFE_TIME_FACTOR, 0, 'Life time factor', od.UNSIGNED8, 'rw', 0))
    d.add_object(
        _record(
            CONSUMER_HEARTBEAT_TIME,
            'Consumer heartbeat time',
            [
                _var(
                    CONSUMER_HEARTBEAT_TIME, 1, 'Consumer heartbeat time 1', od.UNSIGNED32, 'rw', 0
                )
            ],
        )
    )
    d.add_object(
        _var(
            ABORT_CONNECTION_OPTION,
            0,
            'Abort connection option code',
            od.INTEGER16,
            'rw',
            ABORT_FAULT,
        )
    )
    d.add_object(_var(CONTROLWORD, 0, 'Controlword', od.UNSIGNED16, 'rw', 0))
    d.add_object(
        _var(
            STATUSWORD,
            0,
            'Statusword',
            od.UNSIGNED16,
            'ro',
            STATUSWORD_OF_STATE['SWITCH_ON_DISABLED'],
        )
    )
    d.add_object(_var(MODES_OF_OPERATION, 0, 'Modes of operation', od.INTEGER8, 'rw', 0))
    d.add_object(
        _var(MODES_OF_OPERATION_DISPLAY, 0, 'Modes of operation display', od.INTEGER8, 'ro', 0)
    )
    d.add_object(_var(POSITION_ACTUAL, 0, 'Position actual value', od.INTEGER32, 'ro', 0))
    d.add_object(_var(VELOCITY_ACTUAL, 0, 'Velocity actual value', od.INTEGER32, 'ro', 0))
    d.add_object(_var(TARGET_CURRENT, 0, 'Target current', od.INTEGER16, 'rw', 0))
    d.add_object(_var(CURRENT_ACTUAL, 0, 'Current actual value', od.INTEGER16, 'ro', 0))
    d.add_object(
        _record(
            BOARD_INFO,
            'Drive board info',
            [
                _var(
                    BOARD_INFO,
                    BOARD_INFO_MAX_PEAK_CURRENT,
                    'Maximum peak current',
                    od.UNSIGNED16,
                    'ro',
                    round(drive.peak_current_kp),
                ),
                _var(
                    BOARD_INFO,
                    BOARD_INFO_SWITCH_FREQ,
                    'Switching frequency',
                    od.UNSIGNED32,
                    'ro',
                    switching_frequency_pbf(drive.k_s),
                ),
            ],
        )
    )
    d.add_object(
        _record(
            FEEDBACK_PARAMETERS,
            'Feedback parameters',
            [
                _var(
                    FEEDBACK_PARAMETERS,
                    FEEDBACK_POS_INTERPOLATION,
                    'Position interpolation',
                    od.UNSIGNED16,
                    'ro',
                    round(drive.k_i),
                )
            ],
        )
    )
    d.add_object(_var(TIMER1_CYCLE, 0, 'Timer 1 cycle time', od.UNSIGNED32, 'rw', 0))
    d.add_object(_var(TIMER1_TPDOS, 0, 'Timer 1 TPDOs', od.UNSIGNED32, 'rw', 0))
    for offset, index in list(RPDO_COMM.items()) + list(TPDO_COMM.items()):
        d.add_object(
            _record(
                index,
                f'PDO communication 0x{index:04X}',
                [
                    _var(
                        index,
                        1,
                        'COB-ID',
                        od.UNSIGNED32,
                        'rw',
                        cob_id(drive.node_id, offset) | PDO_COB_DISABLED,
                    ),
                    _var(index, 2, 'Transmission type', od.UNSIGNED8, 'rw', PDO_TRANS_ASYNC),
                ],
            )
        )
        mapping_index = index + 0x200
        entries = PDO_MAPPINGS[offset]
        d.add_object(
            _record(
                mapping_index,
                f'PDO mapping 0x{mapping_index:04X}',
                [
                    _var(
                        mapping_index,
                        i + 1,
                        f'Mapped object {i + 1}',
                        od.UNSIGNED32,
                        'ro',
                        (obj << 16) | (sub << 8) | bits,
                    )
                    for i, (obj, sub, bits) in enumerate(entries)
                ],
            )
        )
    return d


def watchdog_steps(watchdog: WatchdogConfig) -> list[StartupStep]:
    """The drive side of the watchdog: heartbeat consumer 0x1016.1 = (bridge node id << 16) | ms,
    or node guarding 0x100C/0x100D, and what to do on a loss (0x6007). Nothing for 'none'."""
    if watchdog.mechanism == 'none':
        return []
    if watchdog.mechanism == 'heartbeat':
        steps = [
            StartupStep(
                'write',
                CONSUMER_HEARTBEAT_TIME,
                1,
                (watchdog.node_id << 16) | watchdog.timeout_ms,
                f'heartbeat consumer: node 0x{watchdog.node_id:02X}, {watchdog.timeout_ms} ms',
            )
        ]
    else:
        steps = [
            StartupStep('write', GUARD_TIME, 0, watchdog.period_ms, 'guard time'),
            StartupStep(
                'write', LIFE_TIME_FACTOR, 0, watchdog.life_time_factor, 'life time factor'
            ),
        ]
    return steps + [
        StartupStep(
            'write',
            ABORT_CONNECTION_OPTION,
            0,
            watchdog.abort_connection_option,
            'abort connection option',
        )
    ]


def startup_sequence(drive: WheelDriveConfig, wheels: WheelsConfig) -> list[StartupStep]:
    """amcdrive_init_drive + amcdrive_start as data: configure the PDOs, the TPDO timer
    (`wheels.tpdo_period_ms`) and the drive-side watchdog (`wheels.watchdog`), enter current mode.

    The drive is started and enabled only once its constants and the objects just written (the
    watchdog's and the TPDO timer's) read back as the config says (the 'verified' step): a drive
    whose watchdog did not take is never enabled.

    Only the current RPDO is enabled (position/velocity RPDOs stay disabled, as in amciod); all
    four TPDOs are enabled (amciod left the current TPDO off; we want the measured current in
    diagnostics). The fault reset (0x80 after 0x06) runs in PRE-OPERATIONAL, where the drive
    ignores the RPDOs (whose controlword 0x008F would mask the rising edge of bit 7), so the same
    sequence is the recovery after a fault.
    """
    n = drive.node_id
    steps = [
        StartupStep('nmt', value=NMT_PRE_OPERATIONAL, what='pre-operational'),
        StartupStep(
            'check', BOARD_INFO, BOARD_INFO_MAX_PEAK_CURRENT, round(drive.peak_current_kp), 'Kp'
        ),
        StartupStep(
            'check', BOARD_INFO, BOARD_INFO_SWITCH_FREQ, switching_frequency_pbf(drive.k_s), 'k_s'
        ),
        StartupStep(
            'check', FEEDBACK_PARAMETERS, FEEDBACK_POS_INTERPOLATION, round(drive.k_i), 'k_i'
        ),
    ]
    for offset, index in RPDO_COMM.items():
        enabled = offset == RPDO_CURRENT
        steps.append(
            StartupStep(
                'write',
                index,
                1,
                cob_id(n, offset) | (0 if enabled else PDO_COB_DISABLED),
                f'RPDO COB-ID 0x{cob_id(n, offset):03X}',
            )
        )
    for offset, index in TPDO_COMM.items():
        steps.append(
            StartupStep(
                'write', index, 1, cob_id(n, offset), f'TPDO COB-ID 0x{cob_id(n, offset):03X}'
            )
        )
    for index in list(RPDO_COMM.values()) + list(TPDO_COMM.values()):
        steps.append(StartupStep('write', index, 2, PDO_TRANS_ASYNC, 'async transmission'))
    watchdog = watchdog_steps(wheels.watchdog)
    period = wheels.tpdo_period_ms
    timer = [
        StartupStep('write', TIMER1_CYCLE, 0, period, f'timer 1 = {period} ms'),
        StartupStep('write', TIMER1_TPDOS, 0, TIMER1_TPDO_BITS, 'timer 1 drives TPDO 1/3/4/5'),
    ]
    steps += watchdog + timer
    # read back what the drive's safety and the samples rest on before it may be enabled
    steps += [
        StartupStep('check', s.index, s.subindex, s.value, f'{s.what} (read back)')
        for s in watchdog + timer
    ]
    steps += [StartupStep('verified', what='constants and written objects as the config says')]
    if wheels.watchdog.mechanism != 'none':
        # a heartbeat consumer (or life guarding) watches only from the first beat it receives
        # after it was configured: no enable before one has gone out
        steps += [StartupStep('armed', what='a watchdog frame sent after it was written')]
    steps += [
        StartupStep('write', CONTROLWORD, 0, CW_SHUTDOWN, 'shutdown'),
        StartupStep('write', CONTROLWORD, 0, CW_RESET_FAULT, 'reset fault'),
        StartupStep('nmt', value=NMT_START, what='start'),
        StartupStep('write', CONTROLWORD, 0, CW_SHUTDOWN, 'shutdown'),
        StartupStep('write', CONTROLWORD, 0, CW_SWITCH_ON, 'switch on'),
        StartupStep('write', MODES_OF_OPERATION, 0, OP_MODE_CURRENT, 'current mode'),
        StartupStep('write', CONTROLWORD, 0, CW_ENABLE_OPERATION, 'enable operation'),
    ]
    return steps


def run_startup(
    network: canopen.Network,
    drive: WheelDriveConfig,
    wheels: WheelsConfig,
    sdo_timeout_s: float = 0.3,
    armed=None,
) -> list[str]:
    """Execute `startup_sequence` through canopen (blocking SDO transfers; run it off the ROS
    executor).

    Returns human-readable mismatches between the drive's constants or the objects it was given
    and the config (the codecs use the config values, so a mismatch means wrong currents or no
    watchdog: the caller must treat it as an error); after any, the drive is left disabled.
    Raises canopen's SdoCommunicationError / SdoAbortedError when the drive does not answer or
    refuses a write. `armed` (no arguments) blocks at the 'armed' step until a watchdog frame has
    gone out after it was called, and raises if none does.
    """
    dictionary = object_dictionary(drive)
    node = canopen.RemoteNode(drive.node_id, dictionary)
    node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
    network.add_node(node)
    mismatches = []
    try:
        for step in startup_sequence(drive, wheels):
            if step.action == 'verified':
                if mismatches:
                    break
            elif step.action == 'armed':
                if armed is not None:
                    armed()
            elif step.action == 'nmt':
                node.nmt.send_command(step.value)
            elif step.action == 'write':
                var = dictionary[step.index]
                if not isinstance(var, od.ODVariable):
                    var = var[step.subindex]
                node.sdo.download(step.index, step.subindex, var.encode_raw(step.value))
            else:
                var = dictionary[step.index]
                if not isinstance(var, od.ODVariable):
                    var = var[step.subindex]
                got = var.decode_raw(node.sdo.upload(step.index, step.subindex))
                if got != step.value:
                    mismatches.append(
                        f'{drive.joint} (node 0x{drive.node_id:02X}): drive reports '
                        f'{step.what} = {got}, config expects {step.value}'
                    )
    finally:
        del network[drive.node_id]
    return mismatches
