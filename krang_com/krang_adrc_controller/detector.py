"""Balanced-pose detector: one data point per pose once the robot has settled.

Why: the learning update needs (joints, q_base) at a balanced rest. At rest on flat ground the
net wheel torque is zero, so the true CoM is over the axle whatever the CoM model says; the
measured IMU pitch q_base then *is* the balance angle (kit README: "q_base is the IMU pitch").

Settled means, over the last ``window_s`` of samples (all of them, contiguous in time):
  * no move under way (the caller's flag: the joints move, or the pose server's target is not
    reached, e.g. a paused move) and every joint within ``joint_tol_rad`` of its window mean;
  * |thetadot| < ``pitch_rate_max`` and |wheel speed| < ``wheel_speed_max`` at every sample;
  * the observer's disturbance estimate has converged: max - min of f_hat over the window below
    ``fhat_band``;
  * the robot is not still slowing down: the mean ground acceleration over the window (the slope
    of the wheel speed) below ``accel_max``. A WIP accelerating
    at a leans about 2 a / g off its balance pitch, so a window that starts as soon as the speed
    drops under ``wheel_speed_max`` (the robot still braking) averaged 0.5-1 mrad off the true
    balance angle in the ROS demo, always on the side of the acceleration;
  * optionally, the std of q_base below ``q_base_std_max``.
Then ONE point is emitted: the window mean of every joint and of q_base, with the standard error
of each mean by batch means (``BATCHES`` contiguous batches; the samples of a swaying robot are
correlated, so std/sqrt(n) would be too small). The detector disarms and
re-arms only when the joints move again (flag set, or a joint leaves ``rearm_tol_rad`` around the
emitted pose). A gap in the samples longer than ``max_gap_s`` (at least three feed periods)
restarts the window.

A robot that cannot come to rest (a limit cycle of a few mrad under the dry friction of a
gearmotor drive chain, which sticks below its breakaway torque) never gives such a window. It
still balances on average: over a stationary window of ``stationary_window_s`` (several cycles)
in which it keeps its place (mean ground speed below ``wheel_speed_max``, every sample's below
``stationary_speed_max``, pitch rate below ``stationary_rate_max``, mean ground acceleration
below ``stationary_accel_max``: on an untold gearmotor chain the first stationary windows after
the stand-up, while the balance point still moved the robot, gave points 2.3-3 mrad off the true
pitch) and the batch-means standard
error of the mean pitch is below ``stationary_se_max``, the window mean is a point too, emitted
with that standard error (so the learner weighs it as it deserves). A robot that does settle gives
its strict point first (2 s against 16 s).

Thresholds are ``DetectorConfig``: our choices, except pitch_rate_max = 0.03 rad/s, the hardware's
"standing still" rate threshold (docs/control.md).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class DetectorConfig:
    """The balanced-pose detector (parameters ``detector.*``), fed in BALANCE only."""

    rate_hz: float = field(
        default=50.0,
        metadata={'doc': 'feed rate, Hz (decimated: the window statistics need no more)'},
    )
    window_s: float = field(default=2.0, metadata={'doc': 'settled window, s'})
    pitch_rate_max: float = field(default=0.03, metadata={'doc': '|pitch rate| bound, rad/s'})
    wheel_speed_max: float = field(
        default=0.008,
        metadata={
            'doc': '|ground speed| bound, m/s: r (mean wheel rate + pitch rate); its noise ~0.0015'
        },
    )
    fhat_band: float = field(
        default=0.6,
        metadata={
            'doc': "max - min of the theta ESO's f_hat over the window, rad/s^2 (noise std 0.065 "
            'at '
            "an ESO bandwidth of 20 rad/s; ~1.9 with the authors' gains)"
        },
    )
    joint_tol_rad: float = field(
        default=2e-3, metadata={'doc': 'every joint within this of its window mean, rad'}
    )
    rearm_tol_rad: float = field(
        default=0.02,
        metadata={'doc': 're-arm when a joint leaves this band around the emitted pose, rad'},
    )
    q_base_std_max: float = field(
        default=0.0, metadata={'doc': 'std bound on q_base over the window, rad (0 = off)'}
    )
    max_gap_s: float = field(
        default=0.2, metadata={'doc': 'a longer gap between samples restarts the window, s'}
    )
    min_samples: int = field(default=10, metadata={'doc': 'fewest samples in a window'})
    accel_max: float = field(
        default=0.0005,
        metadata={
            'doc': '|mean ground acceleration| bound over the window, m/s^2 (a WIP leans about '
            '2 a / g off balance: 0.1 mrad; 0 = off)'
        },
    )

    stationary_window_s: float = field(
        default=16.0,
        metadata={
            'doc': 'stationary window of a robot in a small limit cycle, s (0 = off): four or '
            'more cycles of the 3-4 s one a 0.6 torque and 8 N m of Coulomb friction give, whose '
            'mean then has a standard error the bounds below admit'
        },
    )
    stationary_speed_max: float = field(
        default=0.15, metadata={'doc': '|ground speed| bound at every sample of it, m/s'}
    )
    stationary_rate_max: float = field(
        default=0.3, metadata={'doc': '|pitch rate| bound at every sample of it, rad/s'}
    )
    stationary_accel_max: float = field(
        default=0.002,
        metadata={
            'doc': '|mean ground acceleration| bound over it, m/s^2 (least-squares slope of the '
            'ground speed; 0 = off): a robot still drifting to its place leans about 2 a / g off '
            'its balance pitch'
        },
    )
    stationary_se_max: float = field(
        default=2e-3,
        metadata={
            'doc': 'bound on the standard error of its mean pitch, rad (batch means; the point '
            'carries it, and the learner weighs the point by it)'
        },
    )

    def __post_init__(self):
        if self.window_s <= 0 or self.rate_hz <= 0:
            raise ValueError('detector.window_s and rate_hz must be positive')


#: contiguous batches of the window for the standard errors of its means
BATCHES = 5


def standard_error(samples: np.ndarray) -> np.ndarray:
    """Standard error of the mean of correlated samples (rows in time order) by batch means,
    never below the uncorrelated std/sqrt(n)."""
    n = len(samples)
    naive = samples.std(axis=0, ddof=1) / np.sqrt(n) if n > 1 else np.zeros(samples.shape[1:])
    if n < 2 * BATCHES:
        return naive
    means = np.array([b.mean(axis=0) for b in np.array_split(samples, BATCHES)])
    return np.maximum(means.std(axis=0, ddof=1) / np.sqrt(BATCHES), naive)


@dataclass
class BalancedPoint:
    t: float  # time of the last sample of the window
    q_base: float  # window mean of the base pitch [rad]: the accelerometer's where measured
    joints: np.ndarray  # window mean of the body joints [rad]
    q_base_std: float
    n_samples: int
    window_s: float
    q_base_se: float = 0.0  # standard error of q_base [rad] (standard_error)
    joints_se: np.ndarray | None = None  # ... of the joints [rad]
    q_base_filter: float = math.nan  # window mean of the IMU filter's pitch [rad]
    # read while the joints moved (move_points.py): q_base is then the window mean of the
    # controller's balance-pitch estimate, not of the pitch
    in_motion: bool = False


def _slope(t, v) -> float:
    """Least-squares slope of v over t."""
    t = np.asarray(t, float)
    dt = t - t.mean()
    den = float(dt @ dt)
    return float(dt @ np.asarray(v, float) / den) if den > 0 else 0.0


class BalancedPoseDetector:
    def __init__(self, config: DetectorConfig = DetectorConfig()):
        c = config
        self.window_s = c.window_s
        self.pitch_rate_max = c.pitch_rate_max
        self.wheel_speed_max = c.wheel_speed_max
        self.fhat_band = c.fhat_band
        self.joint_tol = c.joint_tol_rad
        self.rearm_tol = c.rearm_tol_rad
        self.q_base_std_max = c.q_base_std_max or None
        self.max_gap_s = max(c.max_gap_s, 3.0 / c.rate_hz)
        self.min_samples = c.min_samples
        self.accel_max = c.accel_max or None
        self.stationary = (
            c.stationary_window_s,
            c.stationary_speed_max,
            c.stationary_rate_max,
            c.stationary_se_max,
        )
        self.stationary_accel_max = c.stationary_accel_max or None
        self.reset()

    def reset(self) -> None:
        """Forget everything and arm."""
        self._buf: deque = deque()
        self._long: deque = deque()  # the stationary window
        self.armed = True
        self.last_point: BalancedPoint | None = None

    def _clear(self) -> None:
        self._buf.clear()
        self._long.clear()

    def mean_acceleration(self) -> float:
        """Mean ground acceleration over the window, m/s^2: the least-squares slope of the wheel
        speed (every sample counts, so the speed's noise averages out)."""
        return _slope([s[0] for s in self._buf], [s[4] for s in self._buf])

    def update(
        self,
        t: float,
        q_base: float,
        dtheta: float,
        wheel_speed: float,
        fhat: float,
        joints,
        joints_moving: bool,
        gravity_pitch: float = math.nan,
    ) -> BalancedPoint | None:
        """Feed one sample; returns a BalancedPoint exactly once per settled pose, else None.

        gravity_pitch: the accelerometer's pitch (ControlSample.gravity_pitch). In a settled
        window the robot does not accelerate, so the accelerometer reads gravity alone, and its
        mean is the pitch without the gyro drift the IMU filter carries from the move before
        (over ROS 0.18-0.26 mrad off the truth against the filter's 0.37-0.57, 12-pose demo
        bags, docs/learning.md). The point's q_base is that mean whenever every sample of the
        window has one."""
        joints = np.asarray(joints, float).ravel()
        if self._buf and (t - self._buf[-1][0] > self.max_gap_s or t <= self._buf[-1][0]):
            self._clear()
        if not self.armed:
            left = (
                self.last_point is not None
                and np.max(np.abs(joints - self.last_point.joints)) > self.rearm_tol
            )
            if joints_moving or left:
                self.armed = True
                self._clear()
            else:
                return None
        if joints_moving:
            self._clear()
            return None
        if self.stationary[0]:
            point = self._stationary(t, q_base, dtheta, wheel_speed, joints, gravity_pitch)
            if point is not None:
                return point
        still = abs(dtheta) < self.pitch_rate_max and abs(wheel_speed) < self.wheel_speed_max
        if not still:
            self._buf.clear()
            return None
        self._buf.append(
            (float(t), float(q_base), float(fhat), joints, float(wheel_speed), gravity_pitch)
        )
        while self._buf and t - self._buf[0][0] > self.window_s:
            self._buf.popleft()
        # full window: n samples stand for n periods of span/(n-1) each, so require
        # span * n / (n - 1) >= window_s (i.e. within one sample period of window_s)
        span = t - self._buf[0][0]
        n = len(self._buf)
        if n < self.min_samples or span < self.window_s * (1.0 - 1.0 / max(n, 1)):
            return None
        f = np.array([s[2] for s in self._buf])
        if f.max() - f.min() > self.fhat_band:
            return None
        jw = np.vstack([s[3] for s in self._buf])
        jmean = jw.mean(axis=0)
        if np.max(np.abs(jw - jmean)) > self.joint_tol:
            return None
        if self.accel_max is not None and abs(self.mean_acceleration()) > self.accel_max:
            return None
        qb = np.array([s[1] for s in self._buf])
        if self.q_base_std_max is not None and qb.std() > self.q_base_std_max:
            return None
        return self._emit(t, qb, np.array([s[5] for s in self._buf], dtype=float), jw, span)

    def _stationary(self, t, q_base, dtheta, wheel_speed, joints, gravity_pitch):
        """The stationary window's point, or None (see the module docstring)."""
        window, speed_max, rate_max, se_max = self.stationary
        if abs(wheel_speed) > speed_max or abs(dtheta) > rate_max:
            self._long.clear()
            return None
        buf = self._long
        buf.append((t, q_base, wheel_speed, joints, gravity_pitch))
        while buf and t - buf[0][0] > window:
            buf.popleft()
        span = t - buf[0][0]
        n = len(buf)
        if n < self.min_samples or span < window * (1.0 - 1.0 / n):
            return None
        if abs(np.mean([s[2] for s in buf])) > self.wheel_speed_max:
            return None
        amax = self.stationary_accel_max
        if amax is not None and abs(_slope([s[0] for s in buf], [s[2] for s in buf])) > amax:
            return None
        jw = np.vstack([s[3] for s in buf])
        if np.max(np.abs(jw - jw.mean(axis=0))) > self.joint_tol:
            return None
        qb = np.array([s[1] for s in buf])
        gp = np.array([s[4] for s in buf], dtype=float)
        pitch = gp if np.all(np.isfinite(gp)) else qb
        if standard_error(pitch[:, None])[0] > se_max:
            return None
        return self._emit(t, qb, gp, jw, span)

    def _emit(self, t, qb, gp, jw, span):
        """One point from a window: pitch (the accelerometer's where every sample has one) and
        joints, their means and standard errors; then disarm."""
        n = len(qb)
        jmean = jw.mean(axis=0)
        pitch = gp if np.all(np.isfinite(gp)) else qb
        point = BalancedPoint(
            float(t),
            float(pitch.mean()),
            jmean,
            float(pitch.std()),
            n,
            float(span),
            float(standard_error(pitch)),
            standard_error(jw),
            float(qb.mean()),
        )
        self.last_point = point
        self.armed = False
        self._clear()
        return point
