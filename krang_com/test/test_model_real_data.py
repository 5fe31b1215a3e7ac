"""Our Krang description against the authors' own files (skipped without the real-data kit)."""

import csv

import numpy as np
import pytest

from krang_model.beta import load_beta
from krang_model.com import phi, x_com
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang

ALL190 = 'betas/betaVectors1initialBetahardwareAll190Vectors.txt'


@pytest.fixture(scope='module')
def krang():
    return load_krang()


@pytest.fixture(scope='module')
def train(krang_data):
    q_base, joints, _ = load_poses(
        krang_data / 'hardware_balanced_poses_train.csv', KRANG_POSE_COLUMNS
    )
    return q_base, joints


def test_beta_layout_matches_the_authors(krang, krang_data):
    with open(krang_data / 'beta_layout.csv') as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == krang.n_beta
    quantities = {'m': 'm', 'm*x': 'm*x', 'm*y': 'm*y', 'm*z': 'm*z'}
    for row, label, value in zip(rows, krang.beta_labels(), krang.nominal_beta):
        assert label == f'{row["body"]}.{quantities[row["quantity"]]}'
        assert value == pytest.approx(float(row['beta0_value']), rel=1e-5, abs=1e-6)


def test_nominal_beta_is_the_authors_beta0(krang, krang_data):
    np.testing.assert_allclose(
        krang.nominal_beta, load_beta(krang_data / ALL190, krang, row=0), rtol=1e-5, atol=1e-6
    )
    kinect = np.loadtxt(krang_data / 'betas/kinect_96/idealBetaVector.txt')
    without_kinect = np.delete(kinect, np.s_[20:24])  # the Kinect block follows Bracket (body 5)
    np.testing.assert_allclose(krang.nominal_beta, without_kinect, rtol=1e-5, atol=1e-6)
    assert krang.nominal_mass == pytest.approx(162.158, abs=1e-9)


@pytest.mark.parametrize('row, mean_cm, max_cm', [(0, 2.64, 6.26), (189, 0.46, 2.68)])
def test_xcom_errors_equal_the_authors_figures(krang, krang_data, train, row, mean_cm, max_cm):
    beta = load_beta(krang_data / ALL190, krang, row=row)
    err = np.abs(x_com(krang, *train, beta)) * 100
    assert err.mean() == pytest.approx(mean_cm, abs=0.05)
    assert err.max() == pytest.approx(max_cm, abs=0.05)


def test_replaying_the_authors_gradient_descent_reproduces_their_trajectory(
    krang, krang_data, train
):
    """Each of the 189 update directions is phi of one recorded pose: a strict test of our
    kinematics."""
    rows = np.loadtxt(krang_data / ALL190)
    features = phi(krang, *train)
    beta = rows[0].copy()
    worst = 0.0
    for k, f in enumerate(features):
        beta = beta - 300.0 * (f @ beta) * f
        worst = max(worst, np.abs(beta - rows[k + 1]).max())
    assert worst < 3e-4  # the files print 6 significant digits
