"""Our batched kinematics and phi against pinocchio itself and against finite differences."""

import numpy as np
import pinocchio as pin
import pytest

from krang_model.com import (
    balance_pitch,
    base_to_frame0,
    com_error,
    com_frame0,
    lateral_com_error,
    phi,
    x_com,
)
from krang_model.kinematics import body_placements
from krang_model.robot import load_krang, load_wip7


@pytest.fixture(scope='module')
def krang():
    return load_krang()


def random_poses(robot, n, seed=0):
    rng = np.random.default_rng(seed)
    lo = np.maximum(robot.lower, -np.pi)
    hi = np.minimum(robot.upper, np.pi)
    return rng.uniform(-2.0, 0.5, n), rng.uniform(lo, hi, (n, len(lo)))


def pin_root_rotation(q_base):
    """The authors' root orientation RotX(pi/2) RotY(-pi/2 + heading) RotX(-q_base), heading
    0."""
    rx = lambda a: pin.utils.rotate('x', a)  # noqa: E731
    return rx(np.pi / 2) @ pin.utils.rotate('y', -np.pi / 2) @ rx(-q_base)


@pytest.mark.parametrize('make_robot', [load_krang, load_wip7])
def test_body_frames_equal_pinocchio(make_robot):
    robot = make_robot()
    _, joints = random_poses(robot, 20, seed=1)
    rot, trans = body_placements(robot, joints)
    data = robot.model.createData()
    for n, q in enumerate(joints):
        pin.framesForwardKinematics(robot.model, data, robot.pin_configuration(q))
        for b, frame in enumerate(robot.body_frames):
            oMf = data.oMf[robot.model.getFrameId(frame.name, pin.FrameType.BODY)]
            np.testing.assert_allclose(rot[n, b], oMf.rotation, atol=1e-12)
            np.testing.assert_allclose(trans[n, b], oMf.translation, atol=1e-12)


def test_base_to_frame0_is_the_authors_root_rotation():
    for q in (-1.76, -0.8, 0.0, 0.4):
        np.testing.assert_allclose(base_to_frame0([q])[0], pin_root_rotation(q), atol=1e-15)


def test_com_equals_pinocchio_center_of_mass(krang):
    q_base, joints = random_poses(krang, 30, seed=2)
    com = com_frame0(krang, q_base, joints, krang.nominal_beta)
    data = krang.model.createData()
    base = krang.model.inertias[
        0
    ]  # the Base link sits on the universe joint, which centerOfMass skips
    assert base.mass == pytest.approx(75.767)
    for n in range(len(q_base)):
        c_moving = pin.centerOfMass(krang.model, data, krang.pin_configuration(joints[n]))
        c_base = (c_moving * data.mass[0] + base.mass * base.lever) / (data.mass[0] + base.mass)
        np.testing.assert_allclose(com[n], pin_root_rotation(q_base[n]) @ c_base, atol=1e-12)
    # with the nominal beta (total = nominal mass) the paper's x_com is the CoM's x itself
    np.testing.assert_allclose(
        x_com(krang, q_base, joints, krang.nominal_beta), com[:, 0], atol=1e-12
    )


def test_static_regressor_of_pinocchio(krang):
    """pinocchio's computeStaticRegressor @ joint inertia parameters = CoM (it divides by M)."""
    q_base, joints = random_poses(krang, 5, seed=3)
    model = krang.model
    data = model.createData()
    params = np.concatenate(
        [model.inertias[j].toDynamicParameters()[:4] for j in range(1, model.njoints)]
    )
    moving_mass = sum(model.inertias[j].mass for j in range(1, model.njoints))
    for n in range(len(q_base)):
        pin_reg = pin.computeStaticRegressor(model, data, krang.pin_configuration(joints[n]))
        # Base sits on the universe joint, which pinocchio leaves out of the regressor: add it
        # back.
        base = model.inertias[0]
        ours = (
            base_to_frame0([q_base[n]])[0]
            @ (pin_reg @ params * moving_mass + base.mass * base.lever)
            / krang.nominal_mass
        )
        np.testing.assert_allclose(
            com_frame0(krang, q_base[n : n + 1], joints[n : n + 1], krang.nominal_beta)[0],
            ours,
            atol=1e-12,
        )


def test_phi_matches_the_authors_finite_differences(krang):
    """The authors' phi: central differences of M*x_com on m_i and the local CoM c_i, chain-ruled
    to (m, m c) and divided by the nominal mass (krang_model/README.md), computed here through
    pinocchio."""
    q_base, joints = random_poses(krang, 3, seed=4)
    model = krang.model.copy()
    data = model.createData()
    h = 1e-6

    def mass_weighted_x(qb, q):
        c = pin.centerOfMass(model, data, krang.pin_configuration(q))
        base = model.inertias[0]
        return (pin_root_rotation(qb) @ (c * data.mass[0] + base.mass * base.lever))[0]

    ours = phi(krang, q_base, joints)
    for body in ('Spine', 'Bracket', 'L3', 'R6', 'lGripper', 'RWheel'):  # Base: see the CoM test
        b = krang.body_names.index(body)
        jid = krang.body_frames[b].parentJoint
        for n in range(len(q_base)):
            original = model.inertias[jid].copy()
            m, c = original.mass, original.lever.copy()
            grad_c = np.zeros(3)
            for k in range(3):
                for sign in (1, -1):
                    dc = c.copy()
                    dc[k] += sign * h
                    model.inertias[jid] = pin.Inertia(m, dc, original.inertia)
                    grad_c[k] += sign * mass_weighted_x(q_base[n], joints[n]) / (2 * h)
            grad_m = 0.0
            for sign in (1, -1):
                model.inertias[jid] = pin.Inertia(m + sign * h, c, original.inertia)
                grad_m += sign * mass_weighted_x(q_base[n], joints[n]) / (2 * h)
            model.inertias[jid] = original
            # (m, c) -> (m, h = m c): d/dh = (1/m) d/dc, d/dm|h = d/dm|c - (c/m) . d/dc
            expected = np.array([grad_m - c @ grad_c / m, *(grad_c / m)]) / krang.nominal_mass
            np.testing.assert_allclose(ours[n, 4 * b : 4 * b + 4], expected, atol=1e-7)


def test_balance_pitch_balances_with_com_above_the_axle(krang):
    _, joints = random_poses(krang, 200, seed=5)
    rng = np.random.default_rng(6)
    beta = krang.nominal_beta * (1 + 0.05 * rng.standard_normal(krang.n_beta))
    qb = balance_pitch(krang, joints, beta)
    np.testing.assert_allclose(x_com(krang, qb, joints, beta), 0.0, atol=1e-12)
    assert np.all(com_frame0(krang, qb, joints, beta)[:, 2] > 0)


def test_forward_and_lateral_com_errors_separate_the_two_directions(krang):
    """Shift the Base's mass moment along its own x (sideways in frame 0) by 1% of the total mass
    times 1 m: the lateral error is 1 cm at every pose, the forward one stays 0."""
    rng = np.random.default_rng(3)
    joints = rng.uniform(
        np.maximum(krang.lower, -3), np.minimum(krang.upper, 3), (50, len(krang.lower))
    )
    truth = krang.nominal_beta
    sideways = truth.copy()
    sideways[1] += 0.01 * truth[0::4].sum()
    assert com_error(krang, sideways, truth, joints) == pytest.approx(0.0, abs=1e-12)
    assert lateral_com_error(krang, sideways, truth, joints) == pytest.approx(0.01, rel=1e-9)
    assert lateral_com_error(krang, truth, truth, joints) == 0.0
    # a forward error is what x_com measures at the true balance pitch
    forward = truth.copy()
    forward[2:4] *= 1.05
    expected = np.abs(x_com(krang, balance_pitch(krang, joints, truth), joints, forward)).mean()
    assert (
        com_error(krang, forward, truth, joints) == pytest.approx(expected, rel=1e-12)
        and expected > 1e-3
    )


def test_phi_is_fast_and_batched_consistently(krang):
    q_base, joints = random_poses(krang, 1000, seed=7)
    full = phi(krang, q_base, joints)
    parts = np.vstack(
        [phi(krang, q_base[i : i + 100], joints[i : i + 100]) for i in range(0, 1000, 100)]
    )
    np.testing.assert_allclose(full, parts, atol=0)


@pytest.mark.parametrize('make_robot', [load_krang, load_wip7])
def test_fast_phi_equals_the_full_regressor(make_robot):
    """phi propagates one row vector; the full (3, 4B) regressor uses 3x3 frames: two
    implementations."""
    from krang_model.com import regressor

    robot = make_robot()
    q_base, joints = random_poses(robot, 50, seed=8)
    np.testing.assert_allclose(
        phi(robot, q_base, joints),
        regressor(robot, q_base, joints)[:, 0] / robot.nominal_mass,
        atol=1e-14,
    )
