"""Balanced-pose detector: one data point per pose once the robot has settled.

Why: the learning update needs (joints, q_base) at a balanced rest. At rest on flat ground the
net wheel torque is zero, so the true CoM is over the axle whatever the CoM model says; the
measured IMU pitch q_base then *is* the balance angle (kit README: "q_base is the IMU pitch").

Settled means, over the last ``window_s`` of samples (all of them, contiguous in time):
  * joints not moving (the pose server's flag) and every joint within ``joint_tol_rad`` of its
    window mean;
  * |thetadot| < ``pitch_rate_max`` and |wheel speed| < ``wheel_speed_max`` at every sample;
  * the observer's disturbance estimate has converged: max - min of f_hat over the window below
    ``fhat_band``;
  * optionally, the std of q_base below ``q_base_std_max``.
Then ONE point is emitted: the window mean of every joint and of q_base. The detector disarms and
re-arms only when the joints move again (flag set, or a joint leaves ``rearm_tol_rad`` around the
emitted pose). A gap in the samples longer than ``max_gap_s`` restarts the window.

Defaults are our choices (not in FACTS) except pitch_rate_max = 0.03 rad/s, the hardware's
"standing still" rate threshold (FACTS §7).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np


@dataclass
class BalancedPoint:
    t: float                 # time of the last sample of the window
    q_base: float            # window mean of the measured base pitch [rad]
    joints: np.ndarray       # window mean of the body joints [rad]
    q_base_std: float
    n_samples: int
    window_s: float


class BalancedPoseDetector:
    def __init__(self, *, window_s: float = 2.0, pitch_rate_max: float = 0.03,
                 wheel_speed_max: float = 0.05, fhat_band: float = 0.05,
                 joint_tol_rad: float = 2e-3, rearm_tol_rad: float = 0.02,
                 q_base_std_max: float | None = None, max_gap_s: float = 0.2,
                 min_samples: int = 10):
        if window_s <= 0:
            raise ValueError('window_s must be positive')
        self.window_s = window_s
        self.pitch_rate_max = pitch_rate_max
        self.wheel_speed_max = wheel_speed_max
        self.fhat_band = fhat_band
        self.joint_tol = joint_tol_rad
        self.rearm_tol = rearm_tol_rad
        self.q_base_std_max = q_base_std_max
        self.max_gap_s = max_gap_s
        self.min_samples = min_samples
        self.reset()

    def reset(self) -> None:
        """Forget everything and arm."""
        self._buf: deque = deque()
        self.armed = True
        self.last_point: BalancedPoint | None = None

    def _clear(self) -> None:
        self._buf.clear()

    def update(self, t: float, q_base: float, dtheta: float, wheel_speed: float,
               fhat: float, joints, joints_moving: bool) -> BalancedPoint | None:
        """Feed one sample; returns a BalancedPoint exactly once per settled pose, else None."""
        joints = np.asarray(joints, float).ravel()
        if self._buf and (t - self._buf[-1][0] > self.max_gap_s or t <= self._buf[-1][0]):
            self._clear()
        if not self.armed:
            left = (self.last_point is not None
                    and np.max(np.abs(joints - self.last_point.joints)) > self.rearm_tol)
            if joints_moving or left:
                self.armed = True
                self._clear()
            else:
                return None
        if joints_moving:
            self._clear()
            return None
        still = abs(dtheta) < self.pitch_rate_max and abs(wheel_speed) < self.wheel_speed_max
        if not still:
            self._clear()
            return None
        self._buf.append((float(t), float(q_base), float(fhat), joints))
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
        qb = np.array([s[1] for s in self._buf])
        if self.q_base_std_max is not None and qb.std() > self.q_base_std_max:
            return None
        point = BalancedPoint(float(t), float(qb.mean()), jmean, float(qb.std()), n, float(span))
        self.last_point = point
        self.armed = False
        self._clear()
        return point
