"""Pose filtering: Algorithm 1 (fast == straightforward), its stop rule, the other criteria, the
erroneous betas."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

import krang_com_estimator as est
from krang_model.com import phi
from krang_model.robot import load_krang
from krang_pose_server.erroneous_betas import authors_betas, paper_betas
from krang_pose_server.filtering import filter_poses, filter_straightforward
from krang_pose_server.pool import PosePool


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def problem(robot):
    pool = PosePool(robot).generate(1500, seed=21)
    Phi = phi(robot, pool.q_base, pool.joints)
    betas = authors_betas(robot.nominal_beta, 60, np.random.default_rng(5), first_phi=Phi[0])
    return pool, Phi, betas


def test_erroneous_betas_follow_the_authors_recipe(robot, problem):
    _, Phi, betas = problem
    b0 = robot.nominal_beta
    assert betas.shape == (60, robot.n_beta)
    assert np.array_equal(betas[:, 0::4], np.repeat(b0[None, 0::4], 60, 0))  # masses unchanged
    assert np.all(np.abs(betas @ Phi[0]) > 0.02)  # the 2 cm rule
    dev = betas - b0
    moments = np.ones(robot.n_beta, bool)
    moments[0::4] = False
    assert np.all(np.abs(dev[:, moments]) <= 0.5 * np.abs(b0[moments]) + 0.5 + 1e-12)
    p = paper_betas(b0, 200, np.random.default_rng(0))
    rel = p / np.where(b0 == 0, 1, b0) - 1
    assert np.all(np.abs(rel[:, 0::4]) <= 0.2 + 1e-12) and np.abs(rel[:, 0::4]).max() > 0.15
    assert np.array_equal(p[:, 3::4], np.repeat(b0[None, 3::4], 200, 0))  # m*z untouched


@pytest.mark.parametrize('criterion', ['paper-l1', 'squared'])
def test_fast_equals_straightforward(problem, criterion):
    _, Phi, betas = problem
    fast = filter_poses(Phi, betas, criterion)
    ref = filter_straightforward(Phi, betas, criterion)
    assert fast.converged and ref.converged
    assert np.array_equal(fast.selected, ref.selected)
    assert np.allclose(fast.max_error, ref.max_error, rtol=1e-12, atol=1e-15)
    assert np.abs(fast.betas - ref.betas).max() < 1e-12
    if criterion == 'paper-l1':
        assert fast.evaluations < 0.5 * len(Phi) * len(fast.selected)  # it did prune


def test_d_optimal_fast_equals_straightforward_before_saturation(robot, problem):
    _, Phi, betas = problem
    prior = est.physical_prior_std(robot)
    A, b = est.equality_constraints(robot, robot.nominal_mass)
    _, S0 = est.condition_on_constraints(robot.nominal_beta, np.diag(prior**2), A, b)
    r = (math.radians(0.1) * 0.4) ** 2
    fast = filter_poses(
        Phi, betas, 'd-optimal', prior_cov=S0, noise_var=r, x_tol=0.0, max_poses=25
    )
    ref = filter_straightforward(
        Phi, betas, 'd-optimal', prior_cov=S0, noise_var=r, x_tol=0.0, max_poses=25
    )
    assert np.array_equal(fast.selected, ref.selected)
    assert np.abs(fast.betas - ref.betas).max() < 1e-9 * np.abs(ref.betas).max()


def test_stop_rule(problem):
    _, Phi, betas = problem
    res = filter_poses(Phi, betas, 'paper-l1', x_tol=2e-3, window=10)
    err = res.max_error
    assert res.converged
    assert np.all(err[-10:] < 2e-3)
    # it stopped at the first place where 10 in a row were below x_tol
    runs = np.convolve(err < 2e-3, np.ones(10, int), mode='valid')
    assert np.flatnonzero(runs == 10)[0] + 10 == len(err)
    # a tighter tolerance needs more poses; max_poses caps the run
    assert len(filter_poses(Phi, betas, 'paper-l1', x_tol=1e-3).selected) > len(res.selected)
    capped = filter_poses(Phi, betas, 'paper-l1', x_tol=1e-3, max_poses=50)
    assert len(capped.selected) == 50 and not capped.converged


def test_ties_go_to_the_last_pose(problem):
    """The authors' scan keeps the last maximum (>=): duplicate poses pick the later copy."""
    _, Phi, betas = problem
    dup = np.vstack([Phi[:200], Phi[:200]])
    for impl in (filter_poses, filter_straightforward):
        res = impl(dup, betas[:10], 'paper-l1', max_poses=5)
        assert np.all(res.selected[:1] >= 200)


def test_criteria_behave(robot, problem):
    _, Phi, betas = problem
    gd = filter_poses(Phi, betas, 'paper-l1')
    sq = filter_poses(Phi, betas, 'squared')
    # squared: each step removes the most squared error, so after the same number of poses the
    # pool-wide squared error of the hypotheses is no larger than with random poses
    n = 50
    B = betas.T.copy()
    for i in sq.selected[:n]:
        B -= 300 * np.outer(Phi[i], Phi[i] @ B)
    Br = betas.T.copy()
    for i in np.random.default_rng(0).permutation(len(Phi))[:n]:
        Br -= 300 * np.outer(Phi[i], Phi[i] @ Br)
    assert ((Phi @ B) ** 2).sum() < ((Phi @ Br) ** 2).sum()
    # d-optimal: greedy gains are non-increasing (submodularity) and the MAP learner converges fast
    prior = est.physical_prior_std(robot)
    A, b = est.equality_constraints(robot, robot.nominal_mass)
    _, S0 = est.condition_on_constraints(robot.nominal_beta, np.diag(prior**2), A, b)
    r = (math.radians(0.1) * 0.4) ** 2
    d = filter_poses(Phi, betas, 'd-optimal', prior_cov=S0, noise_var=r)
    assert d.converged and len(d.selected) < len(gd.selected)
    S = S0.copy()
    gains = []
    for i in d.selected[:30]:
        v = Phi[i] @ S @ Phi[i]
        gains.append(math.log1p(v / r))
        u = S @ Phi[i]
        S -= np.outer(u, u) / (v + r)
    assert np.all(np.diff(gains) <= 1e-9)
    assert len(set(d.selected.tolist())) == len(d.selected)


def test_cli_filter(tmp_path):
    pool = tmp_path / 'pool.csv'
    subprocess.run(
        [
            sys.executable,
            '-m',
            'krang_cli.main',
            'poses',
            'pool',
            '--n',
            '600',
            '--seed',
            '1',
            '--out',
            str(pool),
            '--no-progress',
            '--json',
        ],
        check=True,
        capture_output=True,
    )
    out = tmp_path / 'filtered.csv'
    res = subprocess.run(
        [
            sys.executable,
            '-m',
            'krang_cli.main',
            'poses',
            'filter',
            '--pool',
            str(pool),
            '--n-betas',
            '40',
            '--seed',
            '2',
            '--tol',
            '0.002',
            '--out',
            str(out),
            '--no-progress',
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc['criterion'] == 'paper-l1' and doc['selected'] > 10 and doc['seconds'] >= 0
    lines = out.read_text().strip().splitlines()
    assert len(lines) == doc['selected'] + 1 and 'pool_index' in lines[0]
