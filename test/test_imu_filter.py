"""Base pitch from DMU samples: kore's geometry with the -45 deg mount, bias removal, the Kalman filter."""
import dataclasses
import math

import numpy as np
import pytest

from krang_can_bridge.config import load_devices
from krang_can_bridge.imu_filter import ImuPitchEstimator, pitch_measurement, sensor_vectors

G = 9.81


def hand_sample(pitch, pitch_rate, mount):
    """Sensor-frame readings built by hand: gravity's reaction g*(sin(p) d + cos(p) z) with the tilt direction
    d = (cos m, -sin m, 0); the rate about the axle e = (cos m, sin m, 0) (kore getImu, inverted)."""
    c, s = math.cos(mount), math.sin(mount)
    force = np.array([G * math.sin(pitch) * c, -G * math.sin(pitch) * s, G * math.cos(pitch)])
    rates = np.array([pitch_rate * c, pitch_rate * s, 0.0])
    return force, rates


@pytest.fixture(scope='module')
def imu():
    return load_devices().imu


def test_measurement_matches_kore_formula_at_minus_45(imu):
    # at m = -45 deg: pitch = atan2((ax + ay)/sqrt2, az), rate = (dQ - dP)/sqrt2
    f = np.array([-3.0, -3.0, 8.0])
    w = np.array([0.2, -0.2, 0.0])
    pitch, rate = pitch_measurement(f, w, imu.mount_angle_rad)
    assert pitch == pytest.approx(math.atan2(-6.0 / math.sqrt(2), 8.0))
    assert rate == pytest.approx(0.4 / math.sqrt(2))
    for p in (-1.76, -0.87, 0.0, 0.5):
        f, w = hand_sample(p, 0.3, imu.mount_angle_rad)
        assert pitch_measurement(f, w, imu.mount_angle_rad) == pytest.approx((p, 0.3))
        sf, sw = sensor_vectors(p, 0.3, imu.mount_angle_rad, G)
        assert sf == pytest.approx(f) and sw == pytest.approx(w)


def run(estimator, pitch_of_t, rate_of_t, mount, bias, duration=3.0, dt=0.002, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    est = None
    for k in range(int(duration / dt)):
        t = k * dt
        f, w = hand_sample(pitch_of_t(t), rate_of_t(t), mount)
        f = f + rng.normal(0, noise * G, 3)
        w = w + np.asarray(bias) + rng.normal(0, noise, 3)
        est = estimator.update(w, f, t)
    return est


def test_constant_pitch_on_the_caster_is_recovered(imu):
    est = run(ImuPitchEstimator(imu), lambda t: -1.76, lambda t: 0.0, imu.mount_angle_rad, imu.gyro_bias_rad_s,
              noise=0.01)
    assert est.ready
    assert est.pitch == pytest.approx(-1.76, abs=0.01)
    assert est.pitch_rate == pytest.approx(0.0, abs=0.02)      # the -0.14 rad/s bias is gone


def test_pitch_ramp_is_tracked(imu):
    rate = 0.2
    est = run(ImuPitchEstimator(imu), lambda t: -1.2 + rate * t, lambda t: rate, imu.mount_angle_rad,
              imu.gyro_bias_rad_s, duration=3.0)
    assert est.pitch == pytest.approx(-1.2 + rate * (3.0 - 0.002), abs=0.005)
    assert est.pitch_rate == pytest.approx(rate, abs=0.01)


def test_mount_angle_is_honoured(imu):
    """Data from a DMU mounted at 0 deg: an estimator configured for 0 recovers the pitch, one configured for
    -45 deg does not (the tilt is read on the wrong axis)."""
    flat = dataclasses.replace(imu, mount_angle_rad=0.0)
    good = run(ImuPitchEstimator(flat), lambda t: -0.7, lambda t: 0.0, 0.0, flat.gyro_bias_rad_s, duration=0.5)
    wrong = run(ImuPitchEstimator(imu), lambda t: -0.7, lambda t: 0.0, 0.0, imu.gyro_bias_rad_s, duration=0.5)
    assert good.pitch == pytest.approx(-0.7, abs=1e-3)
    assert abs(wrong.pitch - -0.7) > 0.1


def test_filter_waits_for_its_initial_average(imu):
    est = ImuPitchEstimator(imu)
    f, w = hand_sample(-0.5, 0.0, imu.mount_angle_rad)
    for k in range(imu.kalman.init_samples - 1):
        assert not est.update(w + imu.gyro_bias_rad_s, f, k * 0.002).ready
    assert est.update(w + imu.gyro_bias_rad_s, f, 1.0).ready


def test_pitch_survives_axle_acceleration():
    """An accelerating axle tilts the accelerometer's pitch by atan(a/g); the configured filter trusts the
    gyro and keeps the pitch error small, where kore's equal weighting (1e-3, 1e-3) follows the tilt."""
    import math

    import numpy as np

    from krang_can_bridge.config import load_devices
    from krang_can_bridge.imu_filter import PitchKalmanFilter, pitch_measurement, sensor_vectors
    cfg = load_devices().imu
    rng = np.random.default_rng(0)

    def rms_error(kalman):
        dt, errors = 0.01, []
        for k in range(4000):
            t = k * dt
            pitch = -1.55 + 0.08 * math.sin(2 * math.pi * 0.4 * t)
            rate = 0.08 * 2 * math.pi * 0.4 * math.cos(2 * math.pi * 0.4 * t)
            accel = 3.0 * math.sin(2 * math.pi * 0.7 * t + 1.0)   # m/s^2 along the floor
            force, rates = sensor_vectors(pitch, rate, cfg.mount_angle_rad, forward_specific_force=accel)
            measured = pitch_measurement(force + rng.normal(0, 0.02, 3), rates + rng.normal(0, 0.002, 3),
                                         cfg.mount_angle_rad)
            estimate, _ = kalman.update(*measured, dt if k else 0.0)
            if t > 10:
                errors.append(estimate - pitch)
        return float(np.sqrt(np.mean(np.square(errors))))
    k = cfg.kalman
    ours = rms_error(PitchKalmanFilter.from_config(k))
    kore = rms_error(PitchKalmanFilter(k.process_k1, k.process_k1b, 1e-3, 1e-3, k.init_samples))
    assert ours < 0.005
    assert kore > 5 * ours
