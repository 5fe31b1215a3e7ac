"""krang learn by default on the 189 hardware poses: a held-out error better than the authors',
every body inside the stated plausible region, and a report of what the data determine; and, on
simulated poses with a known truth, that the directions the data determine are recovered while
the others stay at the prior."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

import krang_com_estimator as est
from krang_com_estimator.identifiability import base_parameters, information_directions
from krang_model.beta import load_beta
from krang_model.com import balance_pitch, x_com
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang

ALL190 = 'betas/betaVectors1initialBetahardwareAll190Vectors.txt'
PAPER_TEST_MEAN_M = 0.004  # the paper's mean |x_com| of its beta_190 on its 46 withheld poses


@pytest.fixture(scope='module')
def robot():
    return load_krang()


def _learn(krang_data, out, *extra):
    cmd = [
        sys.executable,
        '-m',
        'krang_cli.main',
        'learn',
        '--poses',
        str(krang_data / 'hardware_balanced_poses_train.csv'),
        '--beta0',
        str(krang_data / ALL190),
        '--row',
        '0',
        '--out',
        str(out),
        '--json',
        *extra,
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.fixture(scope='module')
def default_learn(krang_data, tmp_path_factory):
    out = tmp_path_factory.mktemp('learn') / 'learned.yaml'
    return _learn(krang_data, out), out


def test_default_learn_beats_the_authors_on_held_out_poses(
    krang_data, tmp_path, default_learn, robot
):
    """The same 10-fold CV for the authors' GD and for the default; the default is also below the
    authors' row 189 on its own training poses and the paper's figure on its withheld poses."""
    doc, _ = default_learn
    gd = _learn(krang_data, tmp_path / 'gd.yaml', '--method', 'paper-gd')
    q, j, _ = load_poses(krang_data / 'hardware_balanced_poses_train.csv', KRANG_POSE_COLUMNS)
    row189 = load_beta(krang_data / ALL190, robot, row=189)
    authors_in_sample = np.abs(x_com(robot, q, j, row189)).mean()
    print(doc['cv_mean_abs_xcom_m'], gd['cv_mean_abs_xcom_m'], authors_in_sample)
    assert doc['method'] == 'map' and doc['cv_folds'] == 10
    assert doc['cv_mean_abs_xcom_m'] < gd['cv_mean_abs_xcom_m']
    assert doc['cv_mean_abs_pitch_deg'] < gd['cv_mean_abs_pitch_deg']
    assert doc['cv_mean_abs_xcom_m'] < authors_in_sample
    assert doc['cv_mean_abs_xcom_m'] < PAPER_TEST_MEAN_M


def test_default_learn_keeps_every_body_plausible(default_learn, robot):
    """No CoM more than 8 cm from CAD, every mass within 20 % of the URDF's, the total mass kept,
    and the bounds the fit touches named."""
    doc, out = default_learn
    beta = load_beta(out, robot)
    assert doc['plausible_region'] == {
        'mass_spread': est.MASS_SPREAD,
        'com_radius_m': est.COM_RADIUS_M,
        'at_bound': doc['plausible_region']['at_bound'],
    }
    assert est.MASS_SPREAD == 0.2 and est.COM_RADIUS_M == 0.08
    assert doc['max_com_moved_m'] <= 0.08 + 1e-6
    assert max(doc['com_moved_m'].values()) <= 0.08 + 1e-6
    lo, hi = est.mass_bounds(robot)
    m = beta[0::4]
    assert np.all(m >= lo * (1 - 1e-6)) and np.all(m <= hi * (1 + 1e-6))
    assert np.all(m > 0)
    cons = est.physical_consistency(robot, beta, mass_spread=0.2, com_radius=0.08)
    assert cons['ok'], cons['violations']
    assert doc['physically_consistent']
    assert beta[0::4].sum() == pytest.approx(robot.nominal_mass, abs=1e-6)
    for body, mass in doc['mass_kg'].items():
        assert mass == pytest.approx(beta[4 * robot.body_names.index(body)], rel=1e-9)
    assert set(doc['plausible_region']['at_bound']) <= {
        f'{b} {what}' for b in robot.body_names for what in ('mass', 'CoM')
    }


def test_default_learn_reports_what_the_data_determine(default_learn):
    ident = default_learn[0]['identifiability']
    assert ident['determined_by_data'] + ident['from_prior'] == ident['directions']
    assert 0 < ident['determined_by_data'] <= 34  # at most the rank of x_com's regressor
    never = set(ident['entries_never_seen'])
    assert {'Base m', 'Base m*x', 'LWheel m', 'Spine m*x'} <= never
    assert never.isdisjoint(ident['entries_from_data'])
    assert 'Base m*y' in ident['entries_from_data']
    ratios = ident['posterior_over_prior_std']
    assert ratios['Base']['m*x'] == pytest.approx(1.0, abs=1e-6)  # never seen: the prior's
    assert ratios['LWheel']['m*y'] is None  # fixed by the wheel-on-axle constraint


def test_determined_directions_are_recovered_and_the_others_stay_at_the_prior(robot):
    """200 simulated poses balanced by a generated truth, 2 mrad of pitch noise: the directions
    the data determine (information_directions) equal the rank of the balanced regressor; along
    each the fit lands within 4 posterior std of the truth; along every other one it stays
    exactly at the prior, although the truth differs there."""
    from krang_pose_server.pool import generate_pool
    from krang_sim.truths import generate_truth

    truth = generate_truth(robot, 7310).beta
    joints = generate_pool(200, seed=13, robot=robot).joints
    sigma = 0.002
    rng = np.random.default_rng(3)
    q = balance_pitch(robot, joints, truth) + sigma * rng.standard_normal(len(joints))
    noise = est.NoiseModel(sigma_imu_rad=sigma)
    fit = est.make_estimator('map', robot, robot.nominal_beta, noise=noise)
    beta, info = fit.fit(q, joints)
    assert not info['inequality_qp']  # the truth is inside the plausible region
    rows, _, var = est.balanced_pose_rows(robot, q, joints, beta, noise)
    lam, V, Z, H0 = information_directions(fit.prior_std, rows, var, fit.A)
    determined = lam >= 1.0
    assert determined.sum() == base_parameters(rows)['rank']
    coord = lambda b: V.T @ H0 @ Z.T @ (b - robot.nominal_beta)  # noqa: E731
    c_fit, c_true = coord(beta), coord(truth)
    z = (c_fit - c_true)[determined] * np.sqrt(1 + lam[determined])
    print(np.round(z, 2))
    assert np.abs(z).max() < 4 and math.sqrt(np.mean(z**2)) < 2
    assert np.abs(c_fit[~determined]).max() < 1e-6
    assert math.sqrt(np.mean(c_true[~determined] ** 2)) > 0.3  # the truth moved there too


def test_map_constrained_keeps_masses_and_coms_in_the_plausible_region(robot):
    """Data that want a 2 cm offset everywhere and a prior so loose that the Gaussian MAP leaves
    the region: the constrained MAP keeps every mass within its spread and every CoM within its
    radius of CAD, with the equality constraints exact."""
    from krang_pose_server.pool import generate_pool

    rng = np.random.default_rng(21)
    joints = generate_pool(40, seed=21, robot=robot).joints
    q = balance_pitch(robot, joints, robot.nominal_beta) + 0.002 * rng.standard_normal(40)
    noise = est.NoiseModel(sigma_imu_rad=math.radians(0.1))
    rows, y, var = est.balanced_pose_rows(robot, q, joints, robot.nominal_beta, noise)
    y = y + 0.02
    prior = est.physical_prior_std(robot, mass_frac=0.5, com_std=1.0)
    A, b = est.equality_constraints(robot, robot.nominal_mass)
    G, h = est.inequality_constraints(robot, mass_spread=0.2)
    balls = est.com_balls(robot, 0.05)
    free, _ = est.map_batch(robot.nominal_beta, prior, rows, y, var, A, b)
    assert not est.within_bounds(free, G, h, balls)
    bounded = est.map_constrained(robot.nominal_beta, prior, rows, y, var, A, b, G, h, balls=balls)
    assert np.all(G @ bounded >= h - 1e-7)
    cons = est.physical_consistency(robot, bounded, mass_spread=0.2, com_radius=0.05 + 1e-6)
    assert cons['ok'], cons['violations']
    assert np.abs(A @ bounded - b).max() < 1e-8
    # and it still follows the data: closer to them than the prior mean
    assert np.abs(rows @ bounded - y).mean() < np.abs(rows @ robot.nominal_beta - y).mean()
