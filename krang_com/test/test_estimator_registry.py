"""The estimator registry: every registered estimator follows the one update protocol, and an
estimator a user registers is offered wherever a method is chosen by name (the CLI's --method)."""

import numpy as np
import pytest

from krang_cli.main import build_parser, main
import krang_com_estimator as est
from krang_com_estimator import registry
from krang_model.com import balance_pitch, phi, x_com
from krang_model.poses import load_poses, save_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_pose_server.pool import PosePool


class NormalisedGD(est.Estimator):
    """A user's estimator: normalised LMS, beta <- beta - (phi^T beta) phi / |phi|^2 (each update
    zeroes the x_com of its own pose)."""

    def update(self, q_base, joints):
        p = phi(self.robot, [q_base], np.atleast_2d(joints))[0]
        err = float(p @ self._beta)
        self._beta -= err * p / float(p @ p)
        self.n_updates += 1
        self.errors.append(err)
        return err


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def data(robot):
    """Exactly consistent data: 30 poses at the exact balance pitch of the nominal beta (the
    truth), and a start beta whose Base mass moment puts the CoM ~1.2 cm off."""
    poses = PosePool(robot).generate(30, seed=4).joints
    truth = robot.nominal_beta
    q = balance_pitch(robot, poses, truth)
    start = truth.copy()
    base = 4 * robot.body_names.index('Base')
    start[base + 2] += robot.nominal_mass * 0.02
    return q, poses, truth, start


@pytest.fixture
def user_estimator():
    est.register_estimator('user-nlms')(NormalisedGD)
    yield 'user-nlms'
    del est.ESTIMATORS['user-nlms']


def _names():
    return list(est.estimator_names()) + ['user-nlms']


def test_the_builtin_estimators_are_registered():
    assert set(est.estimator_names()) >= {'paper-gd', 'paper-gd-mass', 'map', 'map-online'}
    for name, cls in est.ESTIMATORS.items():
        assert issubclass(cls, est.Estimator) and cls.name == name
    with pytest.raises(ValueError, match='unknown estimator'):
        est.make_estimator('nope', None, np.zeros(4))
    with pytest.raises(ValueError, match='already registered'):
        est.register_estimator('paper-gd')(NormalisedGD)


@pytest.mark.parametrize('name', _names())
def test_every_estimator_follows_the_protocol(robot, data, user_estimator, name):
    q, joints, truth, start = data
    # options another estimator takes are dropped, so one set of options serves every method
    e = est.make_estimator(name, robot, truth, eta=300.0, mass_frac=0.1, total_mass=None)
    assert e.name == name
    # at the truth, exactly consistent data leave the estimate where it is
    for qb, jt in zip(q, joints):
        err = e.update(qb, jt)
        assert isinstance(err, float) and abs(err) < 1e-12
    assert e.n_updates == len(q) and len(e.errors) == len(q)
    assert np.abs(e.beta - truth).max() < 1e-9 * np.abs(truth).max()
    cov = e.covariance
    assert cov is None or (
        cov.shape == (robot.n_beta,) * 2 and np.all(np.linalg.eigvalsh(cov) > -1e-9)
    )
    # from a wrong start, the batch fit learns: the CoM error at the poses falls by more than half
    e.reset(start)
    assert np.abs(e.beta - start).max() < 1e-9 * np.abs(start).max()  # MAP: conditioned prior
    assert e.n_updates == 0 and e.errors == []
    beta, info = e.fit(q, joints)
    assert info['method'] == name and info['poses'] == len(q)
    np.testing.assert_array_equal(beta, e.beta)
    before = np.abs(x_com(robot, q, joints, start)).mean()
    after = np.abs(x_com(robot, q, joints, beta)).mean()
    assert before > 0.01 and after < 0.5 * before, (before, after)
    # the default fit is the online updates in order
    if type(e).fit is est.Estimator.fit:
        online = est.make_estimator(name, robot, truth)
        online.reset(start)
        for qb, jt in zip(q, joints):
            online.update(qb, jt)
        np.testing.assert_array_equal(online.beta, beta)


def test_a_user_registered_estimator_is_offered_by_the_cli(robot, data, user_estimator, tmp_path):
    q, joints, truth, start = data
    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices
    for command in ('learn', 'relearn'):
        method = next(a for a in commands[command]._actions if a.dest == 'method')
        assert 'user-nlms' in method.choices and 'map' in method.choices
    poses = tmp_path / 'poses.csv'
    save_poses(poses, q, joints, KRANG_POSE_COLUMNS)
    np.savetxt(tmp_path / 'start.txt', start[None])
    out = tmp_path / 'learned.txt'
    assert (
        main(
            [
                'learn',
                '--poses',
                str(poses),
                '--beta0',
                str(tmp_path / 'start.txt'),
                '--out',
                str(out),
                '--method',
                'user-nlms',
                '--folds',
                '0',
            ]
        )
        == 0
    )
    q_file, joints_file, _ = load_poses(poses, KRANG_POSE_COLUMNS)  # as the CLI read them
    expected, _ = NormalisedGD(robot, start).fit(q_file, joints_file)
    learned = np.loadtxt(out)
    np.testing.assert_allclose(learned, expected, rtol=1e-8, atol=1e-12)  # 9 digits in the file
    assert not np.allclose(learned, start)


def test_entry_point_plugins_are_loaded(monkeypatch):
    """A package names its module in the `krang_com.estimators` entry-point group; the registry
    imports it once, on first use."""
    loaded = []

    class EntryPoint:
        def load(self):
            loaded.append(True)
            est.register_estimator('user-ep')(NormalisedGD)

    monkeypatch.setattr(registry, '_plugins_loaded', False)
    monkeypatch.setattr(
        registry.importlib.metadata,
        'entry_points',
        lambda group: [EntryPoint()] if group == est.ENTRY_POINT_GROUP else [],
    )
    try:
        assert 'user-ep' in est.estimator_names()
        est.estimator_names()
        assert loaded == [True]
    finally:
        est.ESTIMATORS.pop('user-ep', None)
