"""krang_model.wip is one implementation for floats and arrays: a batch of poses, states or
parameter sets gives what the loop of scalar calls gives, and linearize is the model's Jacobian."""

from dataclasses import replace

import numpy as np
import pytest

from krang_model.drivetrain import drivetrain, stack
from krang_model.robot import load_krang
from krang_model.wip import WipDynamics, linearize, reduce_pose, reduce_poses
from krang_sim.scenarios import TABLE2_POSE

# the Table II upper-body pose with the waist at 2.2 rad: balances forward of the caster
POSE = np.concatenate([[2.2], TABLE2_POSE[1:]])  # the Table II pose, waist at 2.2 rad
FIELDS = ('mass', 'com_distance', 'com_offset', 'inertia_axle', 'yaw_inertia', 'com_offset_full')


@pytest.fixture(scope='module')
def krang():
    return load_krang()


@pytest.fixture(scope='module')
def poses(krang):
    rng = np.random.default_rng(4)
    return rng.uniform(krang.lower * 0.5, krang.upper * 0.5, (6, 16))


def parameter_sets(krang):
    """Three drive trains as the discrepancy fit varies them, the caster in contact for one."""
    d = drivetrain(krang)
    return [
        d,
        replace(d, viscous_friction=2.0, coulomb_friction=0.5, floor_slope=0.02),
        replace(d, wheel_radius=0.25, ground_viscous=0.3, torque_constant=0.07),
    ]


def test_reduce_pose_is_reduce_poses_row(krang, poses):
    batch = reduce_poses(krang, poses, krang.nominal_beta)
    assert len(batch) == len(poses)
    for i, pose in enumerate(poses):
        one = reduce_pose(krang, pose, krang.nominal_beta)
        assert one == batch[i]  # bit for bit: a pose's result ignores its batch
        assert all(isinstance(getattr(one, f), float) for f in FIELDS)


def test_batched_dynamics_equal_the_scalar_loop(krang, poses):
    """States (S), poses (B) and parameter sets (P) broadcast as (P, B, S)."""
    bodies = reduce_poses(krang, poses[:3], krang.nominal_beta)
    drives = parameter_sets(krang)
    rng = np.random.default_rng(0)
    S = 5
    states = np.column_stack(
        [
            rng.normal(0, 1, S),
            rng.uniform(-1.9, -0.3, S),
            rng.normal(0, 1, S),
            rng.normal(0, 1, S),
            rng.normal(0, 1, S),
            rng.normal(0, 1, S),
        ]
    )
    states[:2, 1] = -1.80, -1.77  # two on the caster (contact pitch -1.7628)
    tl, tr = rng.normal(0, 20, S), rng.normal(0, 20, S)
    body_b = replace(bodies, **{f: getattr(bodies, f)[None, :, None] for f in FIELDS})
    drive_p = stack(drives)  # differing fields (P, 1) -> (P, 1, 1)
    drive_p = replace(
        drive_p, **{k: v[..., None] for k, v in vars(drive_p).items() if isinstance(v, np.ndarray)}
    )
    batch = WipDynamics(body_b, drive_p)
    acc = batch.accelerations(list(states.T), tl, tr)
    nxt = batch.step(list(states.T), tl, tr, 1e-3)
    assert np.shape(acc[0]) == (3, 3, S)
    touching = 0
    for p, d in enumerate(drives):
        for b in range(3):
            dyn = WipDynamics(bodies[b], d)
            for s in range(S):
                state = [float(v) for v in states[s]]
                touching += dyn.caster_torque(state[1], state[3]) > 0
                ref = dyn.accelerations(state, float(tl[s]), float(tr[s]))
                np.testing.assert_allclose([a[p, b, s] for a in acc], ref, rtol=1e-12, atol=1e-12)
                ref = dyn.step(state, float(tl[s]), float(tr[s]), 1e-3)
                np.testing.assert_allclose([x[p, b, s] for x in nxt], ref, rtol=1e-12, atol=1e-12)
    assert 0 < touching < 3 * 3 * S  # both branches of the caster contact ran


def test_linearize_matches_finite_differences_of_the_scalar_model(krang):
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    for drive in parameter_sets(krang):
        dyn = WipDynamics(body, drive)
        a_lin, b_lin = linearize(body, drive)
        r, upright = drive.wheel_radius, -body.com_offset

        def f(x, tau):
            state = [x[0] / r, upright + x[2], x[1] / r, x[3], 0.0, 0.0]
            ddphi, ddqb, _ = dyn.accelerations(state, tau / 2, tau / 2)
            return np.array([x[1], r * ddphi, x[3], ddqb])

        h = 1e-7  # the Coulomb tanh (0.01 rad/s wide) needs a small step
        a_fd = np.column_stack([(f(h * e, 0.0) - f(-h * e, 0.0)) / (2 * h) for e in np.eye(4)])
        b_fd = (f(np.zeros(4), h) - f(np.zeros(4), -h)) / (2 * h)
        np.testing.assert_allclose(a_lin, a_fd, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(b_lin[:, 0], b_fd, rtol=1e-6, atol=1e-7)


def test_linearize_equals_the_hand_derived_matrices(krang):
    """The closed form of the linearisation (the paper's A(q), B(q) with our friction terms),
    derived by hand: an independent statement of the same physics."""
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    drive = replace(drivetrain(krang), ground_viscous=0.3)
    r, M, dist = drive.wheel_radius, body.mass, body.com_distance
    j = drive.reflected_rotor_inertia
    m11 = (M + drive.wheel_mass) * r**2 + drive.wheel_inertia + j
    m12 = M * r * dist - j
    m22 = body.inertia_axle + j
    inv = np.array([[m22, -m12], [-m12, m11]]) / (m11 * m22 - m12**2)
    b, bg = drive.viscous_friction, drive.ground_viscous
    d_theta = inv @ [0.0, M * drive.gravity * dist]
    d_phidot = inv @ [-(b + bg), b]
    d_thetadot = inv @ [b, -b]
    d_tau = inv @ [1.0, -1.0]
    a = np.array(
        [
            [0, 1, 0, 0],
            [0, d_phidot[0], r * d_theta[0], r * d_thetadot[0]],
            [0, 0, 0, 1],
            [0, d_phidot[1] / r, d_theta[1], d_thetadot[1]],
        ]
    )
    a_lin, b_lin = linearize(body, drive)
    np.testing.assert_allclose(a_lin, a, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(b_lin[:, 0], [0, r * d_tau[0], 0, d_tau[1]], rtol=1e-12)


def test_batched_linearize_equals_the_loop(krang, poses):
    bodies = reduce_poses(krang, poses, krang.nominal_beta)
    drive = drivetrain(krang)
    a, b = linearize(bodies, drive)
    assert a.shape == (len(poses), 4, 4) and b.shape == (len(poses), 4, 1)
    for i in range(len(poses)):
        a1, b1 = linearize(bodies[i], drive)
        np.testing.assert_allclose(a[i], a1, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b[i], b1, rtol=1e-12, atol=1e-12)


def test_stack_keeps_shared_fields_scalar(krang):
    sets = parameter_sets(krang)
    stacked = stack(sets)
    assert isinstance(stacked.gravity, float) and stacked.gravity == sets[0].gravity
    assert stacked.viscous_friction.shape == (3, 1)
    assert stacked.viscous_friction[:, 0].tolist() == [d.viscous_friction for d in sets]
