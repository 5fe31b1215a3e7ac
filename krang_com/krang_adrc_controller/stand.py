"""The stand-up's caster catch and its informed retries (``modes.stand_tries``).

The hardware's stand PD regulates the CoM angle of the ESTIMATED beta to zero. With a CoM error
that puts the true balance pitch close above the caster and the estimate forward of it (truth
7305: 22 mrad above the caster, the estimate 83 mrad forward), the robot lifts off, overshoots
forward, falls back on its caster, and the PD's x and dx terms then push it along on the caster
at full current (the body cannot lift while the wheels accelerate under it) until a stop. A weak
drive chain (a 0.6 torque fraction with 8 N m of dry friction) makes the overshoot larger, so
more truths fail that way.

* *Watch.* From lift-off (IMU pitch ``modes.stand_liftoff_rad`` above the caster's contact
  pitch) the balance-point observer runs beside the stand PD, fed the applied torque. Its drive
  observer separates the chain's torque error, so its raw estimate of the CoM-angle error is
  right within about 0.2 s of lift-off on a chain the controller is not told (gear-hard, truth
  7300: -65..-71 mrad against the true -62). Its mean from ``WATCH_SETTLE_S`` after lift-off is
  the try's estimate.
* *Catch.* Back on the caster after lift-off (the low-passed IMU pitch within
  ``safety.caster_margin_rad`` of the contact for ``safety.caster_catch_s``, the rule of
  BALANCE's catch, caster.py): STAND_UP -> SIT.
* *Slow down on the caster.* The robot is then rolling forward at up to 0.8 m/s, and cutting the
  current, or SIT's brake, tips it forward off the caster: the chain's drag (up to 60 N m at
  that speed) and the brake pitch the body up, and its CoM lies only 20-60 mrad behind the axle
  there. Instead a PI on the pitch holds the body ``modes.stand_catch_hover_rad`` above the
  contact (the stand gains' theta and rate terms, the integral starting from the current at the
  catch so that the drag stays cancelled), which decelerates the robot by as much as its CoM
  lean allows. Stopped (below 0.01 m/s forward) and back on the caster, SIT's ground PD takes
  over, its brake limited to ``modes.stand_catch_brake_a``. Not stopped within
  ``modes.stand_catch_stop_s``: SAFE_STOP (the deceleration is g times the CoM's lean behind the
  axle on the caster, 0.06 m/s^2 for a truth that balances 6 mrad above it).
* *Re-pose.* The pose server reads the estimate (``BalanceController.stand_estimate``) and moves
  the waist so that the CoM, corrected by it, lies where the stand pose meant it to
  (``krang_pose_server.stand_pose.restand_pose``): a CoM only a few mrad behind the axle on the
  caster can neither balance clear of the caster nor brake the rolling robot.
* *Retry.* Once the robot has rested (wheels, pitch and joints still, the re-pose's target
  reached) for ``modes.stand_retry_rest_s``, SIT stands up again. After lift-off the stand PD
  regulates theta minus the estimate, blended in as the body rises from the caster to the
  estimated balance pitch (the full error first: it is the torque that lifts the body against
  the chain's dry friction). An operator's stand_up goes on through the tries as auto_stand
  does. After ``modes.stand_tries`` caught tries the robot stays in SIT with auto_stand suspended
  until the operator's stand_up (or set_enabled), which grants the tries again.
* *Hand over.* A stand-up that reaches BALANCE starts BALANCE's observer at its estimate instead
  of at zero, and BALANCE's x reference is where the robot is then. The stand PD came to rest
  wherever it stood about its reference, and with no CoM-angle term left to balance that offset,
  driving back to where the stand-up began would lean the robot back towards its caster (truth
  7509's retry on a gearmotor chain: the caster 0.55 s after the handover). Handed over at zero,
  BALANCE first regulates about the model's balance pitch while its observer learns the error:
  a truth balancing 34 mrad above its caster in the stand pose (7416) then fell back onto it
  1.3 s after the handover.

Not used (docs/control.md): the drive observer's torque cancelled inside the stand PD (a 2 s limit
cycle of +-80 mrad with the PD's soft gains), the estimate fed into the PD live on the first try
(two nominal truths then fell back as well), a ramped stand reference (the lift-off itself
overshoots).
"""

from __future__ import annotations

from .caster import CasterContact

#: the observer's ESO (20 rad/s) settles in about 3 / 20 s after its reset at lift-off
WATCH_SETTLE_S = 0.2
#: a caught robot counts as stopped below this forward ground speed, m/s
STOPPED_M_S = 0.01
#: ... and as at rest for a retry below this |ground speed|, m/s
REST_M_S = 0.02
#: how the reason of the last caught try ends (the stand_up goal ends on it)
EXHAUSTED = 'auto stand suspended'


class StandUp:
    """The stand-up's bookkeeping across tries (see the module docstring). The controller resets
    and feeds the balance-point observer; this class decides."""

    def __init__(self, modes, safety, caster_pitch: float, period_s: float):
        self.tries_max = int(modes.stand_tries)
        self.caster_pitch = caster_pitch
        self.liftoff_pitch = caster_pitch + modes.stand_liftoff_rad
        self.caster_limit = caster_pitch + safety.caster_margin_rad
        self.catch_s = safety.caster_catch_s
        self.rest_s = modes.stand_retry_rest_s
        self.rest_rate = modes.balance_rate_max
        self.brake_a = modes.stand_catch_brake_a
        self.hover_pitch = self.caster_limit + modes.stand_catch_hover_rad
        self.hover_ki = modes.stand_catch_hover_ki * period_s
        self.tries = 0  # caught tries since the last stand-up that reached BALANCE
        self.trim = 0.0  # the CoM-angle error the next try regulates about after lift-off
        self.lifted_t: float | None = None  # this try's lift-off
        self.last_current = 0.0  # the mean wheel current of the last step, A (the controller's)
        self._hover: float | None = None  # the pitch PI's integral after a catch, A
        self._caught_t = 0.0
        self.stop_s = modes.stand_catch_stop_s
        self._sum = [0.0, 0]  # raw estimates since lift-off + WATCH_SETTLE_S
        self._contact = CasterContact(self.caster_limit, self.catch_s)
        self._rest_since: float | None = None

    @property
    def enabled(self) -> bool:
        return self.tries_max > 0

    @property
    def exhausted(self) -> bool:
        return self.tries >= self.tries_max

    def grant(self) -> None:
        """An operator's stand request: the tries again (the estimate is kept)."""
        self.tries = 0
        self._rest_since = None

    def enter(self) -> None:
        """STAND_UP entered."""
        self.lifted_t = None
        self._sum = [0.0, 0]
        self._contact.reset()
        self._hover = None

    def balanced(self) -> float:
        """STAND_UP -> BALANCE: the CoM-angle error BALANCE's observer starts at (this try's
        estimate; a caught try's if this one was not watched); the tries are granted again."""
        trim = self._sum[0] / self._sum[1] if self._sum[1] else self.trim
        self.tries = 0
        self.trim = 0.0
        return trim

    def lifts_off(self, t: float, q_base: float) -> bool:
        """True on the step the body leaves the caster (the controller resets its observer)."""
        if self.lifted_t is None and q_base > self.liftoff_pitch:
            self.lifted_t = t
            return True
        return False

    def reference(self, q_base: float, theta: float) -> float:
        """The CoM angle the stand PD regulates to: 0, or after lift-off the estimate of a caught
        try (since the last BALANCE), blended in as the body rises from its caster to the
        estimated balance pitch."""
        if not self.trim or self.lifted_t is None:
            return 0.0
        theta_caster = self.caster_pitch + theta - q_base
        if self.trim <= theta_caster:
            return self.trim
        f = (theta - theta_caster) / (self.trim - theta_caster)
        return self.trim * (0.0 if f < 0.0 else (1.0 if f > 1.0 else f))

    def watch(self, t: float, raw: float) -> None:
        """The observer's raw estimate of the CoM-angle error, every lifted step."""
        if self.lifted_t is not None and t - self.lifted_t >= WATCH_SETTLE_S:
            self._sum[0] += raw
            self._sum[1] += 1

    def caught(self, t: float, q_base: float) -> bool:
        """True once, when the lifted body has rested on its caster for caster_catch_s: the try
        failed, and the next one (if any) regulates about this try's estimate."""
        if not self.enabled or self.lifted_t is None or not self.catch_s:
            return False
        if not self._contact.update(t, q_base):
            return False
        if self._sum[1]:
            self.trim = self._sum[0] / self._sum[1]
        self.tries += 1
        self.lifted_t = None
        self._contact.reset()
        self._rest_since = None
        self._hover = self.last_current
        self._caught_t = t
        return True

    def ready(self, t: float, dx: float, dtheta: float, moving: bool = False) -> bool:
        """May SIT stand up again? At once before any catch; after one, once wheels and pitch have
        been still (|dx| < REST_M_S, |pitch rate| < modes.balance_rate_max) and the joints have
        not been `moving` (the pose server's re-pose, its target not reached) for
        stand_retry_rest_s."""
        if not self.tries:
            return True
        if moving or not abs(dx) < REST_M_S or not abs(dtheta) < self.rest_rate:
            self._rest_since = None
            return False
        if self._rest_since is None:
            self._rest_since = t
        return t - self._rest_since >= self.rest_s

    def still_rolling(self, t: float) -> bool:
        """The robot has not slowed down on its caster within stand_catch_stop_s of the catch
        (a body whose CoM lies within a few mrad of the axle on its caster decelerates at only
        g times that angle): the controller stops."""
        return self._hover is not None and self.stop_s > 0 and t - self._caught_t > self.stop_s

    def after_catch(self, u_th, u_x, q_base, dtheta, dx, stand_gains):
        """SIT's ground PD (u_th, u_x, A) after a caught try: while the robot still rolls
        forward, the pitch PI that holds the body just above its caster (with the stand gains'
        theta and rate terms, scaled to the modelled chain); then the brake, limited."""
        if self._hover is not None:
            if dx < STOPPED_M_S and q_base < self.caster_limit:  # stopped, on the caster
                self._hover = None
            else:
                e = q_base - self.hover_pitch
                self._hover += self.hover_ki * e
                return self._hover + stand_gains[0] * e + stand_gains[1] * dtheta, 0.0
        lim = self.brake_a
        return u_th, (-lim if u_x < -lim else (lim if u_x > lim else u_x))

    def why(self) -> str:
        why = (
            f'fell back on its caster after lift-off (try {self.tries} of {self.tries_max}; '
            f'CoM-angle error estimate {self.trim:+.4f} rad)'
        )
        return why + (f'; {EXHAUSTED}' if self.exhausted else '')
