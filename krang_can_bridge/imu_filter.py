"""Base pitch from the DMU: the kore recipe (munzir/36-kore src/sensors.cpp getImu, src/kore.cpp initImu).

Geometry (the DMU is mounted at m = -45 deg about its z axis):
    pitch      = atan2(a_x cos m - a_y sin m, a_z)       (specific force, any unit)
    pitch_rate = w_y sin m + w_x cos m                  (w_x = dQ, w_y = dP, biases removed)
So in sensor coordinates the pitch axis is e = (cos m, sin m, 0), the in-plane tilt direction is
d = (cos m, -sin m, 0), and z points up at pitch 0. Rotating the sensor by +theta about e turns gravity's
reaction into g (sin(theta) d + cos(theta) z): the same pitch atan2 reads, so the rate and the angle agree.
The output is the hardware q_base (kore: qBase := IMU pitch, no offset): about -1.76 rad sitting on the caster,
positive = tilting forward.

Filter: kore's 2-state Kalman filter on (angle, rate), both measured directly, with a constant-rate process
model; process noise from dt with k1 = 2, k1b = 5 and measurement noise 1e-3 on both (FACTS §7). It starts from
the average of the first `init_samples` measurements, as kore did (>= 100 samples).

Unlike imud/kore (which fed raw rates), the configured gyro biases are removed before the filter: ssdmu.c
defines them for this DMU and leaving -0.14 rad/s in the pitch rate would bias the balance controller.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np

from krang_can_bridge.config import ImuConfig, KalmanConfig


def pitch_axis(mount_angle_rad: float) -> np.ndarray:
    """Unit pitch (axle) axis in sensor coordinates."""
    return np.array([math.cos(mount_angle_rad), math.sin(mount_angle_rad), 0.0])


def tilt_direction(mount_angle_rad: float) -> np.ndarray:
    """Unit in-plane direction along which gravity's reaction appears when pitched (sensor coordinates)."""
    return np.array([math.cos(mount_angle_rad), -math.sin(mount_angle_rad), 0.0])


def pitch_measurement(specific_force: Sequence[float], rates: Sequence[float],
                      mount_angle_rad: float) -> tuple[float, float]:
    """(pitch, pitch_rate) of one sample, exactly as kore computed them (specific force in any unit)."""
    m = mount_angle_rad
    new_x = specific_force[0] * math.cos(m) - specific_force[1] * math.sin(m)
    return math.atan2(new_x, specific_force[2]), rates[1] * math.sin(m) + rates[0] * math.cos(m)


def sensor_vectors(pitch: float, pitch_rate: float, mount_angle_rad: float, gravity: float = 9.81,
                   forward_specific_force: float = 0.0, up_specific_force: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(specific force [m/s^2], rates [rad/s]) in sensor coordinates for a robot at `pitch` in the pitch plane.

    The inverse of `pitch_measurement`. Specific force is given in the world pitch plane: `up_specific_force`
    (default `gravity`, i.e. at rest) along world up and `forward_specific_force` along the direction the top of
    the robot moves for positive pitch. Rates other than the pitch rate are zero.
    """
    up = gravity if up_specific_force is None else up_specific_force
    s, c = math.sin(pitch), math.cos(pitch)
    along_tilt = -forward_specific_force * c + up * s      # component on d (d is world -forward at pitch 0)
    along_z = forward_specific_force * s + up * c
    force = along_tilt * tilt_direction(mount_angle_rad) + np.array([0.0, 0.0, along_z])
    return force, pitch_rate * pitch_axis(mount_angle_rad)


class PitchKalmanFilter:
    """kore's filter_kalman on x = (angle, rate), z = (angle, rate), A = [[1, dt], [0, 1]], C = I."""

    def __init__(self, process_k1: float, process_k1b: float, measurement_noise_angle: float,
                 measurement_noise_rate: float, init_samples: int):
        self.k1, self.k1b = process_k1, process_k1b
        self.measurement_cov = np.diag([measurement_noise_angle, measurement_noise_rate])
        self.init_samples = max(1, int(init_samples))
        self._init_sum = np.zeros(2)
        self._init_count = 0
        self.x = np.zeros(2)
        self.P = np.eye(2)

    @classmethod
    def from_config(cls, k: KalmanConfig) -> 'PitchKalmanFilter':
        return cls(k.process_k1, k.process_k1b, k.measurement_noise_angle, k.measurement_noise_rate, k.init_samples)

    @property
    def ready(self) -> bool:
        return self._init_count >= self.init_samples

    def reset(self) -> None:
        self._init_sum[:] = 0.0
        self._init_count = 0
        self.x[:] = 0.0
        self.P = np.eye(2)

    def update(self, angle: float, rate: float, dt: float) -> tuple[float, float]:
        z = np.array([angle, rate], dtype=float)
        if not np.all(np.isfinite(z)):
            return float(self.x[0]), float(self.x[1])
        if not self.ready:
            self._init_sum += z
            self._init_count += 1
            self.x = self._init_sum / self._init_count
            return float(self.x[0]), float(self.x[1])
        if dt > 0.0 and math.isfinite(dt):
            a = np.array([[1.0, dt], [0.0, 1.0]])
            q = np.array([[dt ** 4 * self.k1 / 4.0, dt ** 3 * self.k1 / 2.0],
                          [dt ** 3 * self.k1 / 2.0, dt ** 2 * self.k1b]])
            self.x = a @ self.x
            self.P = a @ self.P @ a.T + q
        gain = self.P @ np.linalg.inv(self.P + self.measurement_cov)
        self.x = self.x + gain @ (z - self.x)
        self.P = (np.eye(2) - gain) @ self.P
        return float(self.x[0]), float(self.x[1])


class PitchEstimate(NamedTuple):
    pitch: float               # q_base [rad], hardware convention
    pitch_rate: float          # dq_base [rad/s]
    raw_pitch: float           # one-sample measurement before the filter
    raw_pitch_rate: float
    ready: bool                # the filter has its initial average
    variance: float            # filter variance of the pitch [rad^2]


class ImuPitchEstimator:
    """Bias removal + kore measurement + Kalman filter, driven by paired DMU samples."""

    def __init__(self, imu: ImuConfig):
        self.mount_angle_rad = imu.mount_angle_rad
        self.gyro_bias = np.array(imu.gyro_bias_rad_s, dtype=float)
        self.filter = PitchKalmanFilter.from_config(imu.kalman)
        self._last_t: float | None = None

    def corrected_rates(self, rates: Sequence[float]) -> np.ndarray:
        return np.asarray(rates, dtype=float) - self.gyro_bias

    def update(self, rates: Sequence[float], specific_force: Sequence[float], t: float) -> PitchEstimate:
        w = self.corrected_rates(rates)
        raw_pitch, raw_rate = pitch_measurement(specific_force, w, self.mount_angle_rad)
        dt = 0.0 if self._last_t is None else t - self._last_t
        self._last_t = t
        pitch, rate = self.filter.update(raw_pitch, raw_rate, dt)
        return PitchEstimate(pitch, rate, raw_pitch, raw_rate, self.filter.ready, float(self.filter.P[0, 0]))
