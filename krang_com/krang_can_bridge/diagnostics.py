"""The CAN bridge core's /diagnostics reports: motion allowed or why not, the arm fault, commands
rejected, frames, the drives' watchdog, each bus, drive, the IMU and each PowerCube module. A
mixin of BridgeCore (krang_can_bridge.bridge), whose state it reads."""

from __future__ import annotations

from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols import powercube as pc
from krang_can_bridge.snapshots import ERROR, OK, STALE, WARN, DiagnosticReport
from krang_core.names import BRIDGE_RECOVER

REJECTION_WARN_S = 10.0  # /diagnostics WARNs this long after a rejected command


class BridgeDiagnostics:
    """BridgeCore's reports."""

    def _silence_text(self, device) -> str:
        if device is self._imu_device and self._imu_frozen:
            return f'{device.name} silent (frozen: {self._imu_frozen})'
        return f'{device.name} silent'

    def diagnostics(self, now: float | None = None) -> list[DiagnosticReport]:
        now = self._now(now)
        c = self.counters
        arm_reason, arm_joints = self.arm_fault(now)
        silent = [d for d in self.devices if d.silent(now)]
        allowed = self.motion_allowed(now)
        fault = (
            [f'drive fault latched: {self._fault} (call {BRIDGE_RECOVER})'] if self._fault else []
        )
        reports = [
            DiagnosticReport(
                'can_bridge: motion',
                OK if allowed else ERROR,
                'motion allowed'
                if allowed
                else 'motion disabled (zero wheel current, no joint motion): '
                + (
                    '; '.join(
                        fault
                        + list(self._inhibits.values())
                        + [self._silence_text(d) for d in silent if self._silence_stops(d, now)]
                    )
                    or 'IMU filter not initialised'
                ),
                {
                    'silent_devices': ', '.join(d.name for d in silent),
                    'inhibits': '; '.join(self._inhibits.values()),
                    'drive_fault': self._fault,
                    'drive_faults_latched': str(c.drive_faults),
                },
            )
        ]
        reports.append(
            DiagnosticReport(
                'can_bridge: arm',
                ERROR if arm_reason else OK,
                f'arm fault latched: {arm_reason}; the wheels keep balancing, '
                f'{", ".join(arm_joints)} held (not measured), no commands to it '
                f'(call {BRIDGE_RECOVER} once every module answers)'
                if arm_reason
                else 'every arm module answering',
                {'arm_fault': arm_reason, 'joints': ', '.join(arm_joints)},
            )
        )
        recent = c.last_rejection_at is not None and now - c.last_rejection_at <= REJECTION_WARN_S
        reports.append(
            DiagnosticReport(
                'can_bridge: commands',
                WARN if recent else OK,
                (
                    f'{c.rejected_commands} rejected commands, last: {c.last_rejection}'
                    if recent
                    else f'{c.rejected_commands} rejected commands, none in the last '
                    f'{REJECTION_WARN_S:.0f} s'
                    if c.rejected_commands
                    else 'no rejected commands'
                ),
                {
                    'rejected_commands': str(c.rejected_commands),
                    'last_rejection': c.last_rejection,
                    'last_rejection_age_s': ''
                    if c.last_rejection_at is None
                    else f'{now - c.last_rejection_at:.3f}',
                    'clamped_commands': str(c.clamped_commands),
                },
            )
        )
        reports.append(
            DiagnosticReport(
                'can_bridge: frames',
                WARN if c.malformed or c.unknown else OK,
                f'{c.malformed} malformed, {c.unknown} unknown of {c.frames}',
                {
                    'frames': str(c.frames),
                    'malformed': str(c.malformed),
                    'unknown': str(c.unknown),
                    'echoes': str(c.echoes),
                    'canopen': str(c.canopen),
                    'last_malformed': c.last_malformed,
                    'last_unknown': c.last_unknown,
                },
            )
        )
        wd = self.config.wheels.watchdog
        beating = (
            wd.mechanism != 'none'
            and self._command_loop_at is not None
            and now - self._command_loop_at <= wd.alive_timeout_s
        )
        reports.append(
            DiagnosticReport(
                'can_bridge: drive watchdog',
                OK if beating or wd.mechanism == 'none' else WARN,
                'off (mechanism none): the drives hold their last current if the bridge dies'
                if wd.mechanism == 'none'
                else f'{wd.mechanism} every {wd.period_ms} ms, drives stop {wd.timeout_ms} ms '
                f'after '
                'the last' + ('' if beating else ': WITHHELD, wheel command loop quiet'),
                {
                    'mechanism': wd.mechanism,
                    'node_id': str(wd.node_id),
                    'abort_connection_option': str(wd.abort_connection_option),
                },
            )
        )
        for bus in self.config.buses_in_use():
            n = c.error_frames.get(bus, 0)
            reports.append(
                DiagnosticReport(
                    f'can_bridge: bus {bus}',
                    WARN if n else OK,
                    f'{n} error frames',
                    {'error_frames': str(n)},
                )
            )
        for joint, w in self._wheels.items():
            state = amc_proto.drive_state(w.statusword) if w.statusword is not None else 'unknown'
            level = (
                STALE
                if w.device.silent(now)
                else OK
                if state == 'OPERATION_ENABLED'
                else ERROR
                if state == 'FAULT'
                else WARN
            )
            reports.append(
                DiagnosticReport(
                    f'can_bridge: {w.device.name}',
                    level,
                    f'drive {state}',
                    {
                        'position_rad': str(w.position),
                        'velocity_rad_s': str(w.velocity),
                        'current_a': str(w.current),
                        'emcy': str(w.emcy),
                        'malformed': str(w.device.malformed),
                    },
                )
            )
        imu = self._imu_snapshot
        level = (
            ERROR
            if self._imu_frozen
            else STALE
            if self._imu_device.silent(now)
            else (OK if imu is not None and imu.ready else WARN)
        )
        reports.append(
            DiagnosticReport(
                'can_bridge: imu',
                level,
                f'frozen: {self._imu_frozen}; its samples are dropped'
                if self._imu_frozen
                else 'silent'
                if level == STALE
                else ('ok' if level == OK else 'initialising'),
                {
                    'pitch_rad': str(imu.pitch if imu else None),
                    'malformed': str(self._imu_device.malformed),
                    'frozen_samples': str(c.frozen_samples),
                    'last_frozen': c.last_frozen,
                },
            )
        )
        for st in self._modules.values():
            not_ok = st.short_state is not None and st.short_state & pc.SHORT_NOT_OK
            silent_now = st.device.silent(now)
            level = (
                ERROR
                if silent_now and st.device.last_seen is not None
                else STALE
                if silent_now
                else (WARN if not_ok else OK)
            )
            reports.append(
                DiagnosticReport(
                    f'can_bridge: {st.device.name}',
                    level,
                    'not answering (arm fault: its joint held at its last position)'
                    if level == ERROR
                    else 'silent'
                    if level == STALE
                    else (
                        'module reports NOT_OK (error, not homed or halted)' if not_ok else 'ok'
                    ),
                    {
                        'position': str(st.position),
                        'short_state': str(st.short_state),
                        'malformed': str(st.device.malformed),
                    },
                )
            )
        return reports
