"""Base pitch from the DMU: the kore recipe (munzir/36-kore src/sensors.cpp getImu,
src/kore.cpp initImu).

Geometry (the DMU is mounted at m = -45 deg about its z axis):
    pitch      = atan2(a_x cos m - a_y sin m, a_z)       (specific force, any unit)
    pitch_rate = w_y sin m + w_x cos m                  (w_x = dQ, w_y = dP, biases removed)
So in sensor coordinates the pitch axis is e = (cos m, sin m, 0), the in-plane tilt direction is
d = (cos m, -sin m, 0), and z points up at pitch 0. Rotating the sensor by +theta about e turns
gravity's reaction into g (sin(theta) d + cos(theta) z): the same pitch atan2 reads, so the rate
and the angle agree. The output is the hardware q_base (kore: qBase := IMU pitch, no offset):
about -1.76 rad sitting on the caster, positive = tilting forward.

Filter: kore's Kalman filter on (angle, rate), both measured directly, with a constant-rate process
model, process noise from dt with k1 = 2, k1b = 5 (docs/imu.md), augmented with the
gyro's residual bias so that a bias the configuration does not know of does not drift the pitch
(`PitchKalmanFilter`, docs/imu.md). It starts from the average of `init_samples` still samples, as
kore averaged >= 100 samples, which also gives the gyro's bias.

Unlike imud/kore (which fed raw rates), the configured gyro biases are removed before the filter:
ssdmu.c defines them for this DMU and leaving -0.14 rad/s in the pitch rate would bias the balance
controller.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple, Sequence

import numpy as np
from scipy.linalg import solve_discrete_are

from krang_can_bridge.config import ImuConfig, KalmanConfig
from krang_can_bridge.sample_clock import SampleClock


def pitch_axis(mount_angle_rad: float) -> np.ndarray:
    """Unit pitch (axle) axis in sensor coordinates."""
    return np.array([math.cos(mount_angle_rad), math.sin(mount_angle_rad), 0.0])


def tilt_direction(mount_angle_rad: float) -> np.ndarray:
    """Unit in-plane direction along which gravity's reaction appears when pitched (sensor
    coordinates)."""
    return np.array([math.cos(mount_angle_rad), -math.sin(mount_angle_rad), 0.0])


def pitch_measurement(
    specific_force: Sequence[float], rates: Sequence[float], mount_angle_rad: float
) -> tuple[float, float]:
    """(pitch, pitch_rate) of one sample, exactly as kore computed them (specific force in any
    unit)."""
    m = mount_angle_rad
    new_x = specific_force[0] * math.cos(m) - specific_force[1] * math.sin(m)
    return math.atan2(new_x, specific_force[2]), rates[1] * math.sin(m) + rates[0] * math.cos(m)


def sensor_vectors(
    pitch: float,
    pitch_rate: float,
    mount_angle_rad: float,
    gravity: float = 9.81,
    forward_specific_force: float = 0.0,
    up_specific_force: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(specific force [m/s^2], rates [rad/s]) in sensor coordinates for a robot at `pitch` in the
    pitch plane.

    The inverse of `pitch_measurement`. Specific force is given in the world pitch plane:
    `up_specific_force` (default `gravity`, i.e. at rest) along world up and
    `forward_specific_force` along the direction the top of
    the robot moves for positive pitch. Rates other than the pitch rate are zero.
    """
    up = gravity if up_specific_force is None else up_specific_force
    s, c = math.sin(pitch), math.cos(pitch)
    along_tilt = -forward_specific_force * c + up * s  # on d (d is world -forward at pitch 0)
    along_z = forward_specific_force * s + up * c
    force = along_tilt * tilt_direction(mount_angle_rad) + np.array([0.0, 0.0, along_z])
    return force, pitch_rate * pitch_axis(mount_angle_rad)


class PitchKalmanFilter:
    """kore's filter_kalman on (angle, rate), augmented with the gyro's residual bias.

    x = (angle, rate, bias); z = (accelerometer angle, gyro rate), the gyro reading rate + bias;
    A = [[1, dt, 0], [0, 1, 0], [0, 0, 1]], C = [[1, 0, 0], [0, 1, 1]]. kore's process noise on
    (angle, rate) (k1, k1b); the bias is a random walk of intensity `bias_process_noise`
    [(rad/s)^2/s]. Without the bias state a gyro bias b integrates into the pitch until the (slow,
    by design) accelerometer correction balances it: 0.001 rad/s gave 27 mrad after 60 s. With it,
    the accelerometer's slow disagreement is put on the gyro and removed; the larger the bias
    noise, the faster, and the more of an accelerating axle's tilt of the accelerometer pitch
    (atan(a/g)) leaks into the pitch (docs/imu.md has the trade-off).

    Start-up (kore averaged >= 100 samples): the filter waits for `init_samples` consecutive
    samples of a still robot: the gyro's means over the window's two halves differ by at most
    `still_rate_change` (not settling onto the caster) and the accelerometer pitch turns slower
    than `still_rate` (not turning). The mean angle then starts the pitch and the mean gyro rate
    the bias (a still gyro reads its bias), with the steady-state covariance. Without a still
    window within `still_wait` s it starts as kore did, from the last window's means, the bias left
    to the tracking.
    """

    _C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]])

    def __init__(
        self,
        process_k1: float,
        process_k1b: float,
        measurement_noise_angle: float,
        measurement_noise_rate: float,
        init_samples: int,
        bias_process_noise: float,
        still_rate: float,
        still_rate_change: float,
        still_wait: float,
    ):
        self.k1, self.k1b = process_k1, process_k1b
        self.bias_process_noise = bias_process_noise
        self.still_rate, self.still_rate_change = still_rate, still_rate_change
        self.still_wait = still_wait
        self.measurement_cov = np.diag([measurement_noise_angle, measurement_noise_rate])
        self.init_samples = max(2, int(init_samples))
        self.reset()

    @classmethod
    def from_config(cls, k: KalmanConfig) -> 'PitchKalmanFilter':
        return cls(
            k.process_k1,
            k.process_k1b,
            k.measurement_noise_angle,
            k.measurement_noise_rate,
            k.init_samples,
            k.bias_process_noise,
            k.still_rate_rad_s,
            k.still_rate_change_rad_s,
            k.still_wait_s,
        )

    @property
    def ready(self) -> bool:
        return self._ready

    @property
    def bias(self) -> float:
        """Residual gyro bias about the pitch axis [rad/s] (beyond the configured biases)."""
        return float(self.x[2])

    def reset(self) -> None:
        self._ready = False
        self._window: deque[tuple[float, float, float]] = deque(maxlen=self.init_samples)
        self._t = 0.0
        self.x = np.zeros(3)
        self.P = np.eye(3)
        self._model_dt = math.nan

    def _start(self, angle: float, rate: float, dt: float) -> None:
        """One start-up sample (t, angle, rate): the window's means in x; start when still."""
        self._t += dt if dt > 0.0 and math.isfinite(dt) else 0.0
        self._window.append((self._t, angle, rate))
        t, angles, rates = np.array(self._window).T
        self.x = np.array([angles.mean(), rates.mean(), 0.0])
        n = len(t)
        if n < self.init_samples:
            return
        half = n // 2
        settling = abs(rates[half:].mean() - rates[:half].mean()) > self.still_rate_change
        turning = t[-1] <= t[0] or abs(np.polyfit(t - t[0], angles, 1)[0]) > self.still_rate
        self._ready = True
        if not (settling or turning):
            self.x = np.array([angles.mean(), 0.0, rates.mean()])
            self.P = self._steady_covariance((t[-1] - t[0]) / (n - 1))
        elif self._t >= self.still_wait:
            self.P = np.diag([1.0, 1.0, self.measurement_cov[1, 1] / n])
        else:
            self._ready = False

    def _model(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        a = np.array([[1.0, dt, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        q = np.array(
            [
                [dt**4 * self.k1 / 4.0, dt**3 * self.k1 / 2.0, 0.0],
                [dt**3 * self.k1 / 2.0, dt**2 * self.k1b, 0.0],
                [0.0, 0.0, dt * self.bias_process_noise],
            ]
        )
        return a, q

    def _steady_covariance(self, dt: float) -> np.ndarray:
        """Steady-state covariance (after the update) at sample period dt. Started from a still
        window, the filter weighs the accelerometer as it will while balancing; kore's unit
        covariance followed the accelerometer through the stand-up's accelerations (70 mrad in
        closed loop)."""
        a, q = self._model(dt)
        c, r = self._C, self.measurement_cov
        try:
            prior = solve_discrete_are(a.T, c.T, q, r)
        except (np.linalg.LinAlgError, ValueError):  # a bias noise too small to solve for
            return np.diag([1.0, 1.0, r[1, 1]])
        return prior - prior @ c.T @ np.linalg.solve(c @ prior @ c.T + r, c @ prior)

    def update(self, angle: float, rate: float, dt: float) -> tuple[float, float]:
        """One sample: the Kalman step in scalars (the bridge runs it per DMU sample)."""
        if not (math.isfinite(angle) and math.isfinite(rate)):
            return float(self.x[0]), float(self.x[1])
        if not self._ready:
            self._start(angle, rate, dt)
            return float(self.x[0]), float(self.x[1])
        x0, x1, x2 = self.x.tolist()
        (p00, p01, p02), (_, p11, p12), (_, _, p22) = self.P.tolist()
        if dt > 0.0 and math.isfinite(dt):  # x <- A x, P <- A P A^T + Q
            if dt != self._model_dt:
                self._model_dt, self._q = dt, self._model(dt)[1].tolist()
            (q00, q01, _), (_, q11, _), (_, _, q22) = self._q
            x0 += dt * x1
            p00 += 2.0 * dt * p01 + dt * dt * p11 + q00
            p01 += dt * p11 + q01
            p02 += dt * p12
            p11 += q11
            p22 += q22
        ra, rw = self.measurement_cov[0, 0], self.measurement_cov[1, 1]
        u = (p00, p01, p02)  # the columns of P C^T
        v = (p01 + p02, p11 + p12, p12 + p22)
        s00, s01, s11 = p00 + ra, p01 + p02, p11 + 2.0 * p12 + p22 + rw
        det = s00 * s11 - s01 * s01
        k0 = [(ui * s11 - vi * s01) / det for ui, vi in zip(u, v)]
        k1 = [(vi * s00 - ui * s01) / det for ui, vi in zip(u, v)]
        y0, y1 = angle - x0, rate - x1 - x2
        self.x = np.array(
            [
                x0 + k0[0] * y0 + k1[0] * y1,
                x1 + k0[1] * y0 + k1[1] * y1,
                x2 + k0[2] * y0 + k1[2] * y1,
            ]
        )
        p = [[p00, p01, p02], [p01, p11, p12], [p02, p12, p22]]
        self.P = np.array(
            [[p[i][j] - k0[i] * u[j] - k1[i] * v[j] for j in range(3)] for i in range(3)]
        )
        return float(self.x[0]), float(self.x[1])


class PitchEstimate(NamedTuple):
    pitch: float  # q_base [rad], hardware convention
    pitch_rate: float  # dq_base [rad/s]
    raw_pitch: float  # one-sample measurement before the filter
    raw_pitch_rate: float
    ready: bool  # the filter has its initial average
    variance: float  # filter variance of the pitch [rad^2]


class ImuPitchEstimator:
    """Bias removal + kore measurement + Kalman filter, driven by paired DMU samples.

    With `sample_period_s` > 0 and each sample's sequence number, the filter steps by the DMU's
    own spacing (sequence counter x period), not by the difference of the sample times it is given:
    the bridge keeps those stamps within 0.04 s of its clock and moves one forward when the
    frames queue up, and a stamp moved 0.02-0.07 s during a pose move integrated the pitch rate
    over that much extra time (10-35 mrad, which the slow accelerometer correction left in the
    next balanced poses; README, Known issues)."""

    def __init__(self, imu: ImuConfig, sample_period_s: float = 0.0):
        self.mount_angle_rad = imu.mount_angle_rad
        self.gyro_bias = np.array(imu.gyro_bias_rad_s, dtype=float)
        self.filter = PitchKalmanFilter.from_config(imu.kalman)
        self._last_t: float | None = None
        # the counter's own time (never held near the caller's clock: only its steps are used)
        self._counter = (
            SampleClock(sample_period_s, lag_max_s=math.inf) if sample_period_s > 0 else None
        )

    def corrected_rates(self, rates: Sequence[float]) -> np.ndarray:
        return np.asarray(rates, dtype=float) - self.gyro_bias

    def update(
        self,
        rates: Sequence[float],
        specific_force: Sequence[float],
        t: float,
        sequence: int | None = None,
    ) -> PitchEstimate:
        """One paired sample at time `t` (numbered `sequence` by the DMU, if known)."""
        w = self.corrected_rates(rates)
        raw_pitch, raw_rate = pitch_measurement(specific_force, w, self.mount_angle_rad)
        if self._counter is not None and sequence is not None:
            t = self._counter.time_of(sequence, t)
        dt = 0.0 if self._last_t is None else t - self._last_t
        self._last_t = t
        pitch, rate = self.filter.update(raw_pitch, raw_rate, dt)
        return PitchEstimate(
            pitch, rate, raw_pitch, raw_rate, self.filter.ready, float(self.filter.P[0, 0])
        )
