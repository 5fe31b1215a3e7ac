"""The balancing controller's operator controls (the node's services) and the offline sessions'
switch: each answers at once with a Reply, accepted or refused with the reason; a long one (stand,
sit) only starts, and the mode reports its progress. A mixin of controller.BalanceController,
whose state it reads and sets."""

from __future__ import annotations

from krang_core.names import BRIDGE_RECOVER

from .modes import Mode
from .samples import Reply


class OperatorRequests:
    """BalanceController's requests (see the module docstring)."""

    def set_enabled(self, enabled: bool, stand: bool | None = None) -> None:
        """Offline sessions' switch, never refused: False -> SAFE_STOP (zero torque) from the next
        step; True -> leave SAFE_STOP to SIT (needs fresh data) and stand up if ``stand`` (default
        ``modes.auto_stand``). Also clears a request_stop() and a drive fault. The operator's
        checked controls are request_enable / request_stand / request_sit / request_stop /
        recover."""
        self.enabled = bool(enabled)
        if self.enabled:
            self._auto_stand = self.config.modes.auto_stand if stand is None else bool(stand)
            self._stand_once = False
            self._stand_asked = False
            self._fault = None
            self._stop_requested = False
            self._sit_requested = False
            self.stand.grant()
            self._reset_pending = True
            self._refused = False
        self._requests()

    def request_enable(self, enabled: bool) -> 'Reply':
        """True: from SAFE_STOP power the loop in SIT without standing up (= recover()); False:
        zero current (SAFE_STOP) from SIT, refused while the robot is off its caster."""
        mode = self.mode
        if enabled:
            if mode is Mode.SAFE_STOP:
                return self.recover()
            return Reply(True, f'already enabled (mode {mode.value})')
        if mode is Mode.SAFE_STOP:
            return Reply(True, 'already disabled (safe_stop, zero current)')
        if mode is not Mode.SIT:
            return Reply(
                False,
                f'refused: the robot is in {mode.value}, off its caster; use sit_down or halt',
            )
        self.set_enabled(False)
        return Reply(True, 'disabled: zero current (safe_stop)')

    def request_stand(self) -> 'Reply':
        """SIT -> STAND_UP, if the CoM-angle error of the latest sample is in the stand window."""
        mode = self.mode
        if mode is not Mode.SIT:
            return Reply(False, f'refused: {self._not_sitting(mode)}')
        out = self.last_output
        if out is None:
            return Reply(False, 'refused: no sensor sample yet')
        if self._stand_once:
            return Reply(False, 'refused: stand_up already requested')
        why = self.modes.stand_refusal(out.theta)
        if why is not None:
            return Reply(False, f'refused: {why}')
        self._stand_once = True
        self._sit_requested = False
        self.stand.grant()  # a stand-up that gave up after its tries gets them again
        self._refused = False
        return Reply(True, 'started: standing up (the mode topic reports stand_up, then balance)')

    def _not_sitting(self, mode: Mode) -> str:
        return {
            Mode.SAFE_STOP: self._stopped_why(),
            Mode.STAND_UP: 'already standing up',
            Mode.BALANCE: 'already balancing',
            Mode.SIT_DOWN: 'sitting down; stand_up once the mode is sit',
        }[mode]

    def _stopped_why(self) -> str:
        if self._fault:
            return (
                f'in safe_stop with a drive fault ({self._fault}); call {BRIDGE_RECOVER}, '
                'then recover'
            )
        return 'in safe_stop (zero current); call recover first'

    def request_sit(self) -> 'Reply':
        """Sit down on the caster (STAND_UP/BALANCE -> SIT_DOWN -> SIT, then the ground PD holds
        with near-zero current), if the waist allows it (modes.py). auto_stand is suspended until
        set_enabled(True)."""
        mode = self.mode
        if mode is Mode.SAFE_STOP:
            return Reply(False, f'refused: {self._stopped_why()}')
        if mode is Mode.SIT or mode is Mode.SIT_DOWN:
            return Reply(
                False, 'refused: already ' + ('sitting' if mode is Mode.SIT else 'sitting down')
            )
        if self._sit_requested:
            return Reply(False, 'refused: sit_down already requested')
        why = self.modes.sit_refusal(self._waist, self.theta_on_caster())
        if why is not None:
            return Reply(False, f'refused: {why}')
        self._sit_requested = True
        self._requests()
        return Reply(True, 'started: sitting down (the mode topic reports sit_down, then sit)')

    def theta_on_caster(self) -> float | None:
        """The CoM angle (rad, whole robot) the current pose would have resting on the caster: the
        model's offset less the balance-point trim; None before the first design."""
        if self._pose is None:
            return None
        trim = self.last_output.balance_trim if self.last_output is not None else 0.0
        return self.drive.caster_pitch + self._offset - trim

    def request_stop(self, reason: str = 'stop requested') -> 'Reply':
        """Latched stop: SAFE_STOP (zero torque) from the next step until recover() (or
        set_enabled(True)). Never refused."""
        if self.mode is Mode.SAFE_STOP and (self._stop_requested or not self.enabled):
            return Reply(True, 'already in safe_stop (zero current)')
        self._stop_requested = True
        self._stop_reason = reason
        self._requests()
        return Reply(True, f'halted: zero current ({reason})')

    def recover(self) -> 'Reply':
        """SAFE_STOP -> SIT, powered and not standing; refused while a drive fault is latched."""
        if self.mode is not Mode.SAFE_STOP:
            return Reply(False, f'refused: not in safe_stop (mode {self.mode.value})')
        if self._fault:
            return Reply(
                False, f'refused: drive fault ({self._fault}); call {BRIDGE_RECOVER} first'
            )
        self.set_enabled(True, stand=False)
        return Reply(True, 'recovering: safe_stop -> sit (powered, on the caster)')

    def set_drive_fault(self, reason: str) -> None:
        """The bridge's latched drive fault: non-empty -> SAFE_STOP with that reason, and recover()
        is refused until it is cleared ('')."""
        if reason:
            if reason != self._fault:
                self.request_stop(f'drive fault: {reason}')
            self._fault = reason
        else:
            self._fault = None

    @property
    def drive_fault(self) -> str | None:
        return self._fault

    def _requests(self) -> None:
        """After any request: can the mode machine be skipped in BALANCE (nothing pending, no fall
        check)?"""
        self._steady = (
            self.enabled
            and not self._stop_requested
            and not self._sit_requested
            and not self._reset_pending
            and self.modes.fall_angle is None
        )
