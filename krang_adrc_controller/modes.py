"""Hardware mode machine: SIT (on the caster) -> STAND_UP -> BALANCE (-> SIT_DOWN -> SIT), plus
a latched SAFE_STOP. Pure: every input is explicit in ``ModeInputs``; no clocks, no I/O.

Guards follow the authors' hardware balancer (munzir/33-beta-testing 01-balance-kore.cpp and
FACTS §7), with thresholds as constructor arguments:

* SIT -> STAND_UP on a stand request only if the CoM-angle (balance) error is in
  [stand_error_min_rad, stand_error_max_rad] = [-10 deg, 0 deg]; otherwise the request is refused.
* STAND_UP -> BALANCE when IMU pitch > balance_imu_min_rad (-101 deg) and |thetadot| <
  balance_rate_max (0.03 rad/s) have held *continuously* for stand_settle_s. FACTS counts
  "> 100 iterations"; at the paper's 0.0333 s loop that is 3.33 s, the default. (The 2018 code
  counted iterations without resetting the counter; a continuous duration is the safe reading
  and does not depend on the loop rate.)
* STAND_UP/BALANCE -> SIT_DOWN on a sit request only if the waist is above sit_waist_min_rad
  (150 deg, FACTS §7); SIT_DOWN -> SIT once the IMU pitch is below sit_imu_limit_rad (-103 deg).
* Any mode -> SAFE_STOP on a stop request or stale sensor data (newest sample older than
  stale_timeout_s). SAFE_STOP commands zero wheel torque and stays latched until a reset request
  arrives with fresh data and no stop request; the robot then restarts in SIT.
* Optional: BALANCE/STAND_UP -> SAFE_STOP when |theta| exceeds fall_angle_rad (off by default:
  not in the authors' code).

Each mode carries the PD current gains of its controller (th, dth, x, dx, psi, dpsi) in A/rad and
A/(rad/s) (FACTS §7); BALANCE says 'adrc'. ``pd_currents`` applies such gains like the hardware.
As on the hardware, the caller re-zeroes the x/psi references when ``entered`` is set, and in
SIT_DOWN uses (IMU pitch - sit_imu_limit_rad) as the theta error of the sit gains.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

DEG = math.pi / 180.0

#: FACTS §7 PD gains (th, dth, x, dx, psi, dpsi) in A per rad / (rad/s).
GROUND_LO_GAINS = (0.0, 0.0, 0.0, -10.0, 0.0, -15.0)
STAND_GAINS = (277.4, 61.889, 7.4484, 18.235, 0.0, 0.0)
SIT_GAINS = (250.0, 40.0, 0.0, 0.0, 0.0, 0.0)
BALANCE_LO_GAINS = (277.4, 61.889, 7.4484, 18.235, 0.0, -10.0)


class Mode(enum.Enum):
    SIT = 'sit'
    STAND_UP = 'stand_up'
    BALANCE = 'balance'
    SIT_DOWN = 'sit_down'
    SAFE_STOP = 'safe_stop'


@dataclass
class ModeInputs:
    """One loop's inputs. Angles in rad, rates in rad/s, times in s (any monotonic clock)."""
    t: float
    imu_pitch: float
    theta_com: float
    dtheta: float
    waist: float | None = None
    last_sensor_t: float | None = None      # newest sensor stamp; None = treat as fresh
    stand_request: bool = False
    sit_request: bool = False
    stop_request: bool = False
    reset_request: bool = False


@dataclass
class ModeOutput:
    mode: Mode
    controller: str                 # 'ground_pd' | 'stand_pd' | 'adrc' | 'sit_pd' | 'off'
    gains: tuple | None             # PD gains of the mode (None for adrc / off)
    zero_torque: bool
    entered: bool                   # True on the step a mode was entered (re-zero x reference,
                                    # reset the ADRC observers)
    events: list = field(default_factory=list)


class ModeMachine:
    """See the module docstring. ``step(inputs) -> ModeOutput``."""

    def __init__(self, *, stand_error_min_rad: float = -10.0 * DEG,
                 stand_error_max_rad: float = 0.0,
                 balance_imu_min_rad: float = -101.0 * DEG,
                 balance_rate_max: float = 0.03,
                 stand_settle_s: float = 100 * 0.0333,
                 sit_waist_min_rad: float = 150.0 * DEG,
                 sit_imu_limit_rad: float = -103.0 * DEG,
                 stale_timeout_s: float = 0.1,
                 fall_angle_rad: float | None = None,
                 ground_gains=GROUND_LO_GAINS, stand_gains=STAND_GAINS, sit_gains=SIT_GAINS,
                 initial_mode: Mode = Mode.SIT):
        self.stand_error_min = stand_error_min_rad
        self.stand_error_max = stand_error_max_rad
        self.balance_imu_min = balance_imu_min_rad
        self.balance_rate_max = balance_rate_max
        self.stand_settle_s = stand_settle_s
        self.sit_waist_min = sit_waist_min_rad
        self.sit_imu_limit = sit_imu_limit_rad
        self.stale_timeout_s = stale_timeout_s
        self.fall_angle = fall_angle_rad
        self.gains = {Mode.SIT: ('ground_pd', tuple(ground_gains)),
                      Mode.STAND_UP: ('stand_pd', tuple(stand_gains)),
                      Mode.BALANCE: ('adrc', None),
                      Mode.SIT_DOWN: ('sit_pd', tuple(sit_gains)),
                      Mode.SAFE_STOP: ('off', None)}
        self.mode = initial_mode
        self._settle_since: float | None = None

    def _stale(self, u: ModeInputs) -> bool:
        return u.last_sensor_t is not None and (u.t - u.last_sensor_t) > self.stale_timeout_s

    def _go(self, mode: Mode, events: list, why: str) -> bool:
        events.append(f'{self.mode.value}->{mode.value}: {why}')
        self.mode = mode
        self._settle_since = None
        return True

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
            entered = self._go(Mode.SAFE_STOP, events, 'stop request' if u.stop_request else 'stale sensors')
        elif (self.fall_angle is not None and self.mode in (Mode.STAND_UP, Mode.BALANCE)
              and abs(u.theta_com) > self.fall_angle):
            entered = self._go(Mode.SAFE_STOP, events, 'fall angle exceeded')
        elif self.mode is Mode.SIT:
            if u.stand_request:
                if self.stand_error_min <= u.theta_com <= self.stand_error_max:
                    entered = self._go(Mode.STAND_UP, events, 'stand request')
                else:
                    events.append('stand_refused: CoM-angle error outside '
                                  f'[{self.stand_error_min:.4f}, {self.stand_error_max:.4f}] rad')
        elif self.mode in (Mode.STAND_UP, Mode.BALANCE) and u.sit_request:
            if u.waist is not None and u.waist > self.sit_waist_min:
                entered = self._go(Mode.SIT_DOWN, events, 'sit request')
            else:
                events.append('sit_refused: waist not above the sit threshold (or unknown)')
        elif self.mode is Mode.STAND_UP:
            ok = u.imu_pitch > self.balance_imu_min and abs(u.dtheta) < self.balance_rate_max
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
        return ModeOutput(self.mode, controller, gains, self.mode is Mode.SAFE_STOP, entered, events)


def pd_currents(gains, error, *, spin_limit_a: float = 30.0,
                current_limit_a: float = 49.0) -> tuple[float, float]:
    """Hardware PD law: (i_left, i_right) from error = state - reference over
    (theta, thetadot, x, xdot, psi, psidot), as in 01-balance-kore.cpp:
    u_theta + u_x +/- u_spin with u_spin = -(K_psi e_psi + K_dpsi e_dpsi) clamped to the spin
    limit (FACTS §7: +/-30 A) and each wheel clamped to the current limit (FACTS §5: 49 A)."""
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
