"""Hardware mode machine: SIT (on the caster) -> STAND_UP -> BALANCE (-> SIT_DOWN -> SIT), plus
a latched SAFE_STOP. Pure: every input is explicit in ``ModeInputs``; no clocks, no I/O.

Guards follow the authors' hardware balancer (munzir/33-beta-testing 01-balance-kore.cpp), with
thresholds in ``ModesConfig`` and ``SafetyConfig``:

* SIT -> STAND_UP on a stand request only if the CoM-angle (balance) error is in
  [stand_error_min_rad, stand_error_max_rad] = [-10 deg, 0 deg]; otherwise the request is refused.
* STAND_UP -> BALANCE when IMU pitch > balance_imu_min_rad (-101 deg) and |thetadot| <
  balance_rate_max (0.03 rad/s) have held *continuously* for stand_settle_s. The hardware counts
  "> 100 iterations", 3.33 s at the paper's 0.0333 s loop. (The 2018 code counted iterations
  without resetting the counter; a continuous duration is the safe reading and does not depend
  on the loop rate.) The default is 1 s: BALANCE starts at the stand-up's own estimate of the
  CoM-angle error, where the robot stands (stand.py, "Hand over"), so a longer wait only keeps
  the soft stand PD in charge, and on a weak drive chain the PD limit-cycles (docs/control.md).
  Once STAND_UP has lasted stand_rate_filter_after_s (5 s), a rate low-passed over
  stand_rate_filter_s (1 s) below the threshold counts too: a drive chain with dry friction
  holds the robot in a limit cycle of a few mrad whose rate crosses 0.03 rad/s every cycle, so
  it would never settle by the instantaneous rate (a 0.6 torque fraction with 8 N m of dry
  friction per wheel timed out after 20 s).
* STAND_UP/BALANCE -> SIT_DOWN on a sit request only if the waist is above sit_waist_min_rad
  (150 deg); SIT_DOWN -> SIT once the IMU pitch is below sit_imu_limit_rad (-103 deg).
* Any mode -> SAFE_STOP on a stop request or stale sensor data (newest sample older than
  stale_timeout_s). SAFE_STOP commands zero wheel torque and stays latched until a reset request
  arrives with fresh data and no stop request; the robot then restarts in SIT.
* Ours: BALANCE/STAND_UP -> SAFE_STOP when |theta| exceeds fall_angle_rad (0.6 rad; not in the
  authors' code): a robot that fell (seen on the full-body plant: forward onto its front, wheels
  stalled by their friction) is otherwise held at the current limit for as long as it lies.
* Ours: BALANCE -> SIT when the caller reports the body resting on its caster (``on_caster``,
  ``SafetyConfig.caster_catch_s``): the robot sits where it is instead of running away. The
  same from STAND_UP once the body had lifted off (``ModesConfig.stand_tries``; the caller's
  stand.py decides when SIT stands up again).

Each mode carries the PD current gains of its controller (th, dth, x, dx, psi, dpsi) in A/rad and
A/(rad/s) (01-balance-kore.cpp); BALANCE says 'adrc'. ``pd_currents`` applies such gains like
the hardware. The thresholds above are the hardware's; ``ModesConfig`` says where ours differ.
As on the hardware, the caller re-zeroes the x/psi references when ``entered`` is set, and in
SIT_DOWN uses (IMU pitch - sit_imu_limit_rad) as the theta error of the sit gains.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field, fields

import numpy as np

DEG = math.pi / 180.0

#: The hardware's PD gains (th, dth, x, dx, psi, dpsi) in A per rad / (rad/s), 01-balance-kore.cpp.
GROUND_LO_GAINS = (0.0, 0.0, 0.0, -10.0, 0.0, -15.0)
STAND_GAINS = (277.4, 61.889, 7.4484, 18.235, 0.0, 0.0)
SIT_GAINS = (250.0, 40.0, 0.0, 0.0, 0.0, 0.0)


def _doc(text):
    return {'doc': text}


#: the 2018 hardware's settle time before BALANCE: "> 100 iterations" of its 30 Hz loop, s
HARDWARE_STAND_SETTLE_S = 3.33


@dataclass(frozen=True)
class ModesConfig:
    """Mode guards and the PD gains of the modes (parameters ``modes.*``). PD gains are (th, dth,
    x, dx, psi, dpsi) in A/rad and A/(rad/s). Where our robot differs from the 2018 hardware's
    guards, the reason is given."""

    auto_stand: bool = field(
        default=True,
        metadata=_doc(
            'when enabled and sitting, ask to stand (the joystick button on the hardware)'
        ),
    )
    start_enabled: bool = field(
        default=False, metadata=_doc('false = start in SAFE_STOP until enabled')
    )
    stand_error_min_rad: float = field(
        default=-0.20944,
        metadata=_doc(
            "stand only if the CoM-angle error is above this, rad. -12 deg, the authors' sim: in "
            'our '
            'sim the robot sits at q_base -1.7628 and balances at -1.568 with the true beta, '
            'theta = '
            "-11.2 deg on the caster, so the hardware's -10 deg would refuse a perfect model"
        ),
    )
    stand_error_max_rad: float = field(
        default=0.0, metadata=_doc('stand only if the CoM-angle error is below this, rad')
    )
    balance_imu_min_rad: float = field(
        default=-1.76278,
        metadata=_doc('STAND_UP -> BALANCE needs the IMU pitch above this, rad (-101 deg)'),
    )
    balance_rate_max: float = field(
        default=0.03,
        metadata=_doc('... and |pitch rate| below this, rad/s, continuously for stand_settle_s'),
    )
    stand_settle_s: float = field(
        default=1.0,
        metadata=_doc(
            f'settle time before BALANCE, s (the 2018 hardware: {HARDWARE_STAND_SETTLE_S} s)'
        ),
    )
    stand_rate_filter_s: float = field(
        default=1.0,
        metadata=_doc(
            'time constant of a low-pass of the pitch rate the settle check also accepts, s '
            "(0 = only the hardware's instantaneous rate, which a drive chain with dry friction "
            'never meets)'
        ),
    )
    stand_rate_filter_after_s: float = field(
        default=5.0,
        metadata=_doc(
            'the settle check accepts the low-passed rate once STAND_UP has lasted this long, s '
            "(0 = from the start): a stand-up that settles by the hardware's rate is unchanged"
        ),
    )
    stand_tries: int = field(
        default=3,
        metadata=_doc(
            'stand-ups that fall back on the caster after lift-off before the robot stays in '
            'SIT (ours; 0 = no caster catch in STAND_UP, as on the hardware). A caught try goes '
            'to SIT and slows down on its caster instead of being pushed along it at full '
            'current; the next try regulates about the CoM-angle error the balance-point '
            'observer saw while the body was off the caster (stand.py)'
        ),
    )
    stand_liftoff_rad: float = field(
        default=0.01,
        metadata=_doc(
            "lift-off: IMU pitch this far above the caster's contact pitch, rad (from then on "
            'the observer watches and the caster catch is armed)'
        ),
    )
    stand_retry_rest_s: float = field(
        default=1.0,
        metadata=_doc('after a caught stand-up, stand again once at rest this long, s'),
    )
    stand_catch_hover_rad: float = field(
        default=0.001,
        metadata=_doc(
            'after a caught stand-up, while the robot rolls forward, a pitch PI holds the body '
            "this far above the caster's contact (plus safety.caster_margin_rad), rad: it "
            "decelerates the robot as far as its CoM lean allows and cancels the chain's drag, "
            'which would otherwise tip the body forward off the caster'
        ),
    )
    stand_catch_hover_ki: float = field(
        default=3000.0,
        metadata=_doc(
            "... the PI's integral gain, A/(rad s) (its proportional and rate gains are the "
            "stand gains'); it starts from the current at the catch"
        ),
    )
    stand_catch_stop_s: float = field(
        default=20.0,
        metadata=_doc(
            '... and SAFE_STOP if the robot still rolls forward this long after the catch, s '
            '(0 = never): the PI decelerates by g times the CoM lean behind the axle, nearly '
            'nothing for a robot that balances within a few mrad of its caster'
        ),
    )
    stand_catch_brake_a: float = field(
        default=2.0,
        metadata=_doc(
            "after a caught stand-up, once the robot has slowed down, SIT's ground PD brakes "
            'with at most this per wheel, A: the full brake pitches a body whose CoM lies a '
            'few degrees behind the axle forward off its caster'
        ),
    )
    sit_waist_min_rad: float = field(
        default=2.61799, metadata=_doc('sit down only with the waist above this, rad (150 deg)')
    )
    sit_theta_max_rad: float = field(
        default=-0.05,
        metadata=_doc(
            'sit down only if the CoM angle the model predicts on the caster is below this, rad '
            '(ours): nearer the axle the robot lands on its caster, bounces off past its balance '
            'point and tips forward under the ground PD (over ROS in the sim at -0.02 rad)'
        ),
    )
    sit_rate_rad_s: float = field(
        default=0.2,
        metadata=_doc(
            'SIT_DOWN lowers its pitch reference from the pitch at the sit request to '
            "sit_imu_limit_rad at this rate, rad/s (ours; 0 = the hardware's step). From the "
            "sim's start pose the step lands at 0.80 rad/s, no gentler than a torque-free fall "
            '(0.74); 0.2 rad/s lands at 0.37 (docs/control.md)'
        ),
    )
    sit_imu_limit_rad: float = field(
        default=-1.75406,
        metadata=_doc(
            'SIT_DOWN -> SIT below this IMU pitch, rad. -100.5 deg: the hardware used -103 deg, '
            'but '
            "the sim's caster holds the robot at -101.1 deg, so -103 deg is never reached"
        ),
    )
    ground_gains: tuple[float, ...] = field(
        default=GROUND_LO_GAINS, metadata=_doc("PD gains in SIT (the hardware's GroundLo)")
    )
    stand_gains: tuple[float, ...] = field(
        default=STAND_GAINS, metadata=_doc('PD gains in STAND_UP')
    )
    sit_gains: tuple[float, ...] = field(default=SIT_GAINS, metadata=_doc('PD gains in SIT_DOWN'))
    spin_gains: tuple[float, ...] = field(
        default=(0.0, -10.0),
        metadata=_doc("(psi, dpsi) spin PD in BALANCE (the hardware's BalLo), A/rad, A/(rad/s)"),
    )
    spin_limit_a: float = field(default=30.0, metadata=_doc('|spin current| clamp, A'))

    def __post_init__(self):
        for name in ('ground_gains', 'stand_gains', 'sit_gains'):
            if len(getattr(self, name)) != 6:
                raise ValueError(f'modes.{name} needs 6 gains (th, dth, x, dx, psi, dpsi)')
        if len(self.spin_gains) != 2:
            raise ValueError('modes.spin_gains needs (psi, dpsi)')
        if (
            self.stand_tries < 0
            or self.stand_liftoff_rad <= 0
            or self.stand_retry_rest_s < 0
            or self.stand_catch_brake_a < 0
            or self.stand_catch_hover_rad < 0
            or self.stand_catch_hover_ki < 0
            or self.stand_catch_stop_s < 0
        ):
            raise ValueError(
                'modes.stand_tries, stand_retry_rest_s and stand_catch_* must not be negative, '
                'stand_liftoff_rad must be positive'
            )


@dataclass(frozen=True)
class SafetyConfig:
    """Stops (parameters ``safety.*``); 0 = off where noted. stand_timeout_s and max_speed_m_s
    are ours, not in the 2018 code: a stand-up that does not settle, or a runaway (e.g. the robot
    pushed along on its caster when the estimated CoM angle is near 0), ends in SAFE_STOP."""

    stale_timeout_s: float = field(
        default=0.1, metadata=_doc('SAFE_STOP when the newest sensor sample is older than this, s')
    )
    fall_angle_rad: float = field(
        default=0.6,
        metadata=_doc(
            'SAFE_STOP when |theta| exceeds this in STAND_UP/BALANCE, rad (0 = off, as in the '
            '2018 code): a body this far off its balance has fallen, and BALANCE would hold the '
            'saturated current into it'
        ),
    )
    stand_timeout_s: float = field(
        default=20.0,
        metadata=_doc('SAFE_STOP when STAND_UP has not settled within this, s (0 = off)'),
    )
    max_speed_m_s: float = field(
        default=3.0,
        metadata=_doc('SAFE_STOP above this |ground speed| in STAND_UP/BALANCE, m/s (0 = off)'),
    )
    caster_catch_s: float = field(
        default=0.1,
        metadata=_doc(
            'BALANCE -> SIT when the IMU pitch has stayed within caster_margin_rad of the caster '
            "contact this long, s (0 = off): the pose's true balance pitch lies beyond the caster "
            '(a CoM error during a pose move), and balancing on would push the robot along on its '
            'caster at full current until max_speed_m_s. STAND_UP -> SIT likewise after lift-off '
            '(modes.stand_tries)'
        ),
    )
    caster_margin_rad: float = field(
        default=0.003,
        metadata=_doc(
            "caster contact: the IMU pitch, low-passed over 20 ms (caster.py), below the caster's "
            'contact pitch plus this, rad'
        ),
    )

    def __post_init__(self):
        if self.stale_timeout_s <= 0:
            raise ValueError('safety.stale_timeout_s must be positive')
        if any(getattr(self, f.name) < 0 for f in fields(self)):
            raise ValueError('safety limits must not be negative')


class Mode(enum.Enum):
    SIT = 'sit'
    STAND_UP = 'stand_up'
    BALANCE = 'balance'
    SIT_DOWN = 'sit_down'
    SAFE_STOP = 'safe_stop'


#: the modes as numbers, for logs and numeric columns (a safe stop below zero)
MODE_CODES = {'safe_stop': -1, 'sit': 0, 'stand_up': 1, 'balance': 2, 'sit_down': 3}


@dataclass
class ModeInputs:
    """One loop's inputs. Angles in rad, rates in rad/s, times in s (any monotonic clock)."""

    t: float
    imu_pitch: float
    theta_com: float
    dtheta: float
    waist: float | None = None
    last_sensor_t: float | None = None  # newest sensor stamp; None = treat as fresh
    stand_request: bool = False
    sit_request: bool = False
    stop_request: bool = False
    reset_request: bool = False
    on_caster: bool = False  # BALANCE, STAND_UP (after lift-off): the body rests on its caster


@dataclass
class ModeOutput:
    mode: Mode
    controller: str  # 'ground_pd' | 'stand_pd' | 'adrc' | 'sit_pd' | 'off'
    gains: tuple | None  # PD gains of the mode (None for adrc / off)
    zero_torque: bool
    entered: bool  # True on the step a mode was entered (re-zero x reference,
    # reset the ADRC observers)
    events: list = field(default_factory=list)


class ModeMachine:
    """See the module docstring. ``step(inputs) -> ModeOutput``."""

    def __init__(
        self,
        config: ModesConfig = ModesConfig(),
        safety: SafetyConfig = SafetyConfig(),
        initial_mode: Mode = Mode.SIT,
    ):
        self.stand_error_min = config.stand_error_min_rad
        self.stand_error_max = config.stand_error_max_rad
        self.balance_imu_min = config.balance_imu_min_rad
        self.balance_rate_max = config.balance_rate_max
        self.stand_settle_s = config.stand_settle_s
        self.stand_rate_filter_s = config.stand_rate_filter_s
        self.stand_rate_filter_after_s = config.stand_rate_filter_after_s
        self._rate_lp: tuple | None = None  # (t, low-passed pitch rate) in STAND_UP
        self._stand_t0 = 0.0  # when STAND_UP was entered
        self.sit_waist_min = config.sit_waist_min_rad
        self.sit_imu_limit = config.sit_imu_limit_rad
        self.sit_theta_max = config.sit_theta_max_rad
        self.stale_timeout_s = safety.stale_timeout_s
        self.fall_angle = safety.fall_angle_rad or None
        self.gains = {
            Mode.SIT: ('ground_pd', tuple(config.ground_gains)),
            Mode.STAND_UP: ('stand_pd', tuple(config.stand_gains)),
            Mode.BALANCE: ('adrc', None),
            Mode.SIT_DOWN: ('sit_pd', tuple(config.sit_gains)),
            Mode.SAFE_STOP: ('off', None),
        }
        self.mode = initial_mode
        self._settle_since: float | None = None

    def stand_refusal(self, theta_com: float) -> str | None:
        """Why SIT -> STAND_UP is refused at this CoM-angle error, or None (the hardware's
        window)."""
        if self.stand_error_min <= theta_com <= self.stand_error_max:
            return None
        return (
            f'CoM-angle error {theta_com:+.4f} rad outside '
            f'[{self.stand_error_min:.4f}, {self.stand_error_max:.4f}] rad'
        )

    def sit_refusal(self, waist: float | None, theta_on_caster: float | None = None) -> str | None:
        """Why STAND_UP/BALANCE -> SIT_DOWN is refused with this waist angle and predicted CoM
        angle on the caster (None: not checked), or None."""
        if waist is None or waist <= self.sit_waist_min:
            return (
                f'waist {"unknown" if waist is None else f"{waist:.3f} rad"} not above the '
                f'sit threshold {self.sit_waist_min:.3f} rad'
            )
        if theta_on_caster is not None and theta_on_caster > self.sit_theta_max:
            return (
                f'on the caster the CoM would be only {-theta_on_caster:.3f} rad behind the '
                f'axle (needs {-self.sit_theta_max:.3f}): it could tip forward off the '
                'caster; move to a pose with the CoM further back first'
            )
        return None

    def _stale(self, u: ModeInputs) -> bool:
        return u.last_sensor_t is not None and (u.t - u.last_sensor_t) > self.stale_timeout_s

    def _go(self, mode: Mode, events: list, why: str) -> bool:
        events.append(f'{self.mode.value}->{mode.value}: {why}')
        self.mode = mode
        self._settle_since = None
        self._rate_lp = None
        return True

    def _still(self, u: ModeInputs) -> bool:
        """The settle check's rate: the instantaneous one, or (late in STAND_UP) the low-passed
        one, below balance_rate_max."""
        limit = self.balance_rate_max
        if not self.stand_rate_filter_s:
            return abs(u.dtheta) < limit
        lp = self._rate(u)  # every step, so the filter is current when it counts
        if abs(u.dtheta) < limit:
            return True
        return u.t - self._stand_t0 >= self.stand_rate_filter_after_s and abs(lp) < limit

    def _rate(self, u: ModeInputs) -> float:
        """The pitch rate low-passed over stand_rate_filter_s."""
        tau = self.stand_rate_filter_s
        if self._rate_lp is None or not 0.0 < u.t - self._rate_lp[0] < 1.0:
            self._rate_lp = (u.t, u.dtheta)
        else:
            t0, r = self._rate_lp
            r += (1.0 - math.exp(-(u.t - t0) / tau)) * (u.dtheta - r)
            self._rate_lp = (u.t, r)
        return self._rate_lp[1]

    def step(self, u: ModeInputs) -> ModeOutput:
        events: list = []
        entered = False
        stale = self._stale(u)
        if self.mode is Mode.SAFE_STOP:
            if u.reset_request and not stale and not u.stop_request:
                entered = self._go(Mode.SIT, events, 'reset')
            elif u.reset_request:
                events.append('reset_refused: ' + ('stale sensors' if stale else 'stop requested'))
        elif u.stop_request or stale:
            entered = self._go(
                Mode.SAFE_STOP, events, 'stop request' if u.stop_request else 'stale sensors'
            )
        elif (
            self.fall_angle is not None
            and self.mode in (Mode.STAND_UP, Mode.BALANCE)
            and abs(u.theta_com) > self.fall_angle
        ):
            entered = self._go(Mode.SAFE_STOP, events, 'fall angle exceeded')
        elif self.mode is Mode.BALANCE and u.on_caster:
            entered = self._go(Mode.SIT, events, 'caster contact while balancing')
        elif self.mode is Mode.STAND_UP and u.on_caster:
            entered = self._go(Mode.SIT, events, 'fell back on the caster while standing up')
        elif self.mode is Mode.SIT:
            if u.stand_request:
                why = self.stand_refusal(u.theta_com)
                if why is None:
                    entered = self._go(Mode.STAND_UP, events, 'stand request')
                    self._stand_t0 = u.t
                else:
                    events.append('stand_refused: ' + why)
        elif self.mode in (Mode.STAND_UP, Mode.BALANCE) and u.sit_request:
            why = self.sit_refusal(u.waist)
            if why is None:
                entered = self._go(Mode.SIT_DOWN, events, 'sit request')
            else:
                events.append('sit_refused: ' + why)
        elif self.mode is Mode.STAND_UP:
            ok = self._still(u) and u.imu_pitch > self.balance_imu_min
            if not ok:
                self._settle_since = None
            else:
                if self._settle_since is None:
                    self._settle_since = u.t
                if u.t - self._settle_since >= self.stand_settle_s:
                    entered = self._go(Mode.BALANCE, events, 'stood up and settled')
        elif self.mode is Mode.SIT_DOWN:
            if u.imu_pitch < self.sit_imu_limit:
                entered = self._go(Mode.SIT, events, 'on the caster')
        controller, gains = self.gains[self.mode]
        return ModeOutput(
            self.mode, controller, gains, self.mode is Mode.SAFE_STOP, entered, events
        )


def pd_currents(
    gains, error, *, spin_limit_a: float, current_limit_a: float
) -> tuple[float, float]:
    """Hardware PD law: (i_left, i_right) from error = state - reference over
    (theta, thetadot, x, xdot, psi, psidot), as in 01-balance-kore.cpp:
    u_theta + u_x +/- u_spin with u_spin = -(K_psi e_psi + K_dpsi e_dpsi) clamped to the spin
    limit (``ModesConfig.spin_limit_a``) and each wheel clamped to the drive train's current
    limit."""
    k = np.asarray(gains, float).ravel()
    e = np.asarray(error, float).ravel()
    if k.size != 6 or e.size != 6:
        raise ValueError('gains and error need 6 elements (th, dth, x, dx, psi, dpsi)')
    u_th = k[0] * e[0] + k[1] * e[1]
    u_x = k[2] * e[2] + k[3] * e[3]
    u_spin = float(np.clip(-(k[4] * e[4] + k[5] * e[5]), -spin_limit_a, spin_limit_a))
    left = float(np.clip(u_th + u_x + u_spin, -current_limit_a, current_limit_a))
    right = float(np.clip(u_th + u_x - u_spin, -current_limit_a, current_limit_a))
    return left, right
