"""The estimator's per-pose pitch uncertainty, the evidence-calibrated noise and prior scales, the
IMU pitch-offset term and the per-body shift uncertainty (krang_com_estimator), on
simulated balanced poses with a known truth, and on the real hardware poses (kit)."""

import math

import numpy as np
import pytest

import krang_com_estimator as est
from krang_model.com import balance_pitch
from krang_model.robot import load_krang
from krang_pose_server.pool import generate_pool
from krang_sim.truths import generate_truth


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def sim_poses(robot):
    """200 pool poses balanced by a generated truth; the true balance pitches."""
    truth = generate_truth(robot, 7300).beta
    joints = generate_pool(200, seed=11, robot=robot).joints
    return truth, joints, balance_pitch(robot, joints, truth)


def test_a_pose_with_a_large_standard_error_barely_counts(robot, sim_poses):
    truth, joints, q = sim_poses
    m = est.make_estimator('map-online', robot, robot.nominal_beta)
    for k in range(5):
        m.update(q[k], joints[k])
    before = m.beta
    m.update(q[5] + 0.05, joints[5], sigma=10.0)  # 50 mrad off, sigma 10 rad
    assert np.abs(m.beta - before).max() < 1e-6 * np.abs(before).max()
    # the per-pose sigma is kept for the re-linearisation: finalize = batch Gauss-Newton with it
    m.update(q[6], joints[6], sigma=1e-3)
    beta = m.finalize()
    sig = np.array([math.nan] * 5 + [10.0, 1e-3])
    ref, _, _ = est.map_gauss_newton(
        robot, q[:7], joints[:7], m.beta0, m.prior_std, m.noise, m.A, m.b, sigma_pitch=sig
    )
    np.testing.assert_allclose(beta, ref, atol=1e-8 * np.abs(ref).max())
    assert est.NoiseModel().pitch_std([np.nan, 3e-3], 2) == pytest.approx(
        [math.radians(0.1), math.hypot(math.radians(0.1), 3e-3)]
    )


def test_evidence_maximisation_finds_the_pitch_noise(robot, sim_poses):
    truth, joints, q = sim_poses
    rng = np.random.default_rng(5)
    for sigma in (0.002, 0.006):
        q_meas = q + sigma * rng.standard_normal(len(q))
        cal = est.calibrate_scales(
            robot,
            q_meas,
            joints,
            robot.nominal_beta,
            *est.equality_constraints(robot, robot.nominal_mass),
        )
        print(sigma, cal)
        assert cal['sigma_pitch_rad'] == pytest.approx(sigma, rel=0.25)


def test_pitch_offset_is_estimated_with_its_uncertainty(robot, sim_poses):
    truth, joints, q = sim_poses
    rng = np.random.default_rng(6)
    offset = 0.015
    q_meas = q + offset + 0.002 * rng.standard_normal(len(q))
    noise = est.NoiseModel(sigma_imu_rad=0.002)
    with_offset = est.make_estimator(
        'map', robot, robot.nominal_beta, noise=noise, pitch_offset_std=0.035
    )
    beta, info = with_offset.fit(q_meas, joints)
    print(info['pitch_offset_rad'], info['pitch_offset_std_rad'])
    assert abs(info['pitch_offset_rad'] - offset) < 3 * info['pitch_offset_std_rad']
    assert info['pitch_offset_std_rad'] < 0.01
    plain, _ = est.make_estimator('map', robot, robot.nominal_beta, noise=noise).fit(
        q_meas, joints
    )
    held = generate_pool(300, seed=12, robot=robot).joints
    from krang_model.com import com_error

    assert com_error(robot, beta, truth, held) < com_error(robot, plain, truth, held)


def test_com_shift_std_matches_sampling(robot, sim_poses):
    truth, joints, q = sim_poses
    m = est.make_estimator('map', robot, robot.nominal_beta)
    beta, _ = m.fit(q[:30], joints[:30])
    std = est.com_shift_std(robot, beta, m.covariance)
    rng = np.random.default_rng(0)
    cov = m.covariance
    w, v = np.linalg.eigh(cov)
    draws = beta + (rng.standard_normal((4000, len(beta))) * np.sqrt(np.clip(w, 0, None))) @ v.T
    i = robot.body_names.index('Base')
    ref = robot.nominal_beta[4 * i + 1 : 4 * i + 4] / robot.nominal_beta[4 * i]
    d = beta[4 * i + 1 : 4 * i + 4] / beta[4 * i] - ref
    u = d / np.linalg.norm(d)
    proj = (draws[:, 4 * i + 1 : 4 * i + 4] / draws[:, [4 * i]] - ref) @ u
    assert std[i] == pytest.approx(proj.std(), rel=0.1)


def test_calibrated_fit_of_the_hardware_poses_stays_plausible(robot, krang_data):
    """The 189 hardware poses: the calibration searches only mass stds within half the plausible
    mass spread (the evidence alone takes 46 %, and the fit then puts the Spine at +83 %); the
    calibrated MAP keeps the in-sample fit, every mass within 20 % of the URDF's and no body's CoM
    more than 8 cm from CAD."""
    from krang_model.beta import load_beta
    from krang_model.com import x_com
    from krang_model.poses import load_poses
    from krang_model.robot import KRANG_POSE_COLUMNS

    b0 = load_beta(
        krang_data / 'betas' / 'betaVectors1initialBetahardwareAll190Vectors.txt', robot, row=0
    )
    q, j, _ = load_poses(krang_data / 'hardware_balanced_poses_train.csv', KRANG_POSE_COLUMNS)
    beta, info = est.make_estimator('map', robot, b0, calibrate=True).fit(q, j)
    cons = est.physical_consistency(
        robot, beta, mass_spread=est.MASS_SPREAD, com_radius=est.COM_RADIUS_M
    )
    moved = max(b['com_moved_m'] for b in cons['bodies'])
    print(info['calibration'], moved, np.abs(x_com(robot, q, j, beta)).mean(), cons['at_bound'])
    assert info['calibration']['mass_frac'] <= est.MASS_SPREAD / 2 + 1e-9
    assert cons['ok'], cons['violations']
    assert moved <= est.COM_RADIUS_M + 1e-6
    assert np.abs(x_com(robot, q, j, beta)).mean() < 0.0020


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_calibrated_fit_of_the_hardware_poses_cross_validates_better(robot, krang_data):
    """10-fold CV with the calibration inside every fold: mean |x_com| <= 0.23 cm (the MAP
    without the plausible region)."""
    from krang_model.beta import load_beta
    from krang_model.poses import load_poses
    from krang_model.robot import KRANG_POSE_COLUMNS

    b0 = load_beta(
        krang_data / 'betas' / 'betaVectors1initialBetahardwareAll190Vectors.txt', robot, row=0
    )
    q, j, _ = load_poses(krang_data / 'hardware_balanced_poses_train.csv', KRANG_POSE_COLUMNS)
    pred, _ = est.cross_validate('map', robot, q, j, b0, folds=10, seed=0, calibrate=True)
    print(np.abs(pred).mean(), np.abs(pred).max())
    assert np.abs(pred).mean() <= 0.0023
