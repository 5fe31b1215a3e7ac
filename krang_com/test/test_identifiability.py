"""Identifiability of beta from balanced poses: rank, base parameters and the report in words."""

import json
import subprocess
import sys

import numpy as np
import pytest

from krang_com_estimator import identifiability as ident
from krang_model.robot import load_krang


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def report(robot):
    return ident.analyse(robot, n=1500, seed=0)


def test_rank_of_the_stacked_regressor(robot, report):
    phi_arb = ident.sample_regressor(robot, 1500, 0, 'arbitrary')
    phi_bal = ident.sample_regressor(robot, 1500, 0, 'balanced')
    # an independent rank: singular values with a clear gap
    for P, rank in ((phi_arb, report['rank_arbitrary']), (phi_bal, report['rank_balanced'])):
        s = np.linalg.svd(P, compute_uv=False)
        assert s[rank - 1] / s[0] > 1e-6
        assert s[rank] / s[0] < 1e-10
    assert report['rank_balanced'] == report['rank_arbitrary'] - 1  # the scale direction
    assert report['rank_arbitrary'] < robot.n_beta
    # the same rank from another random sample
    assert (
        ident.base_parameters(ident.sample_regressor(robot, 1500, 1, 'arbitrary'))['rank']
        == report['rank_arbitrary']
    )


def test_known_unidentifiable_entries_are_reported(report):
    for name in (
        'Base m',
        'Base m*x',
        'Spine m*x',
        'LWheel m',
        'RWheel m',
        'LWheel m*x',
        'RWheel m*x',
    ):
        assert name in report['unidentifiable']
    text = '\n'.join(report['lines'])
    assert 'Base m*x (axle direction): not identifiable — phi is always 0' in text
    assert 'Spine m*x (axle direction): not identifiable — phi is always 0' in text


def test_combinations_are_true_null_directions(robot, report):
    """Each reported combination 'p acts like sum c_k q_k' is a null direction of the regressor."""
    Phi = ident.sample_regressor(robot, 800, 5, 'arbitrary')
    names = robot.beta_labels()
    index = {ident.describe_entry(robot, j): j for j in range(robot.n_beta)}
    assert len(report['combinations']) > 0
    for combo in report['combinations']:
        v = np.zeros(robot.n_beta)
        v[index[combo['parameter']]] = 1.0
        for other, c in combo['acts_like']:
            v[index[other]] -= c
        # the report drops coefficients below 1e-6 (relative) for readability, and the URDF's rpy
        # values (3.14159265, 1.5707963) make some axes parallel only to ~1e-8: residual at that
        # level, versus order 1 for a pair that is not dependent
        assert np.linalg.norm(Phi @ v) < 1e-6 * np.linalg.norm(Phi) * np.linalg.norm(v), combo
    assert len(names) == robot.n_beta
    # e.g. the L5/L6 pair along the LJ6 axis
    assert any(
        c['parameter'] == 'L6 m*x' and c['acts_like'][0][0] == 'L5 m*x'
        for c in report['combinations']
    )


def test_scale_is_not_fixed_by_the_total_mass(report):
    assert report['scale_direction_residual_balanced'] < 1e-12
    assert report['scale_direction_residual_arbitrary'] > 1e-3
    assert (
        report['rank_moments_masses_known_balanced']
        == report['rank_moments_masses_known_arbitrary'] - 1
    )


def test_cli_json():
    out = subprocess.run(
        [sys.executable, '-m', 'krang_cli.main', 'identifiability', '--n', '600', '--json'],
        capture_output=True,
        text=True,
        check=True,
    )
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert doc['rank_balanced'] == doc['rank_arbitrary'] - 1
    assert 'Base m*x' in doc['unidentifiable']
