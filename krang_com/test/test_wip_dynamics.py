"""The WIP reduction, nonlinear dynamics and linearisation against independent references."""

import math
from dataclasses import replace

import numpy as np
import pinocchio as pin
import pytest

from krang_model.com import balance_pitch, com_frame0
from krang_model.robot import load_krang, load_wip7
from krang_model.drivetrain import HeldCommand, command_delay_steps, drivetrain, stack
from krang_model.wip import WipDynamics, linearize, reduce_pose
from krang_sim.scenarios import TABLE2_POSE

POSE = np.array(
    [
        2.65,
        1.17,
        -1.6,
        1.58,
        1.68,
        -1.13,
        3.13,
        -1.19,
        0.03,
        1.26,
        -1.67,
        2.10,
        -0.70,
        -1.19,
        1.43,
        -1.67,
    ]
)


@pytest.fixture(scope='module')
def krang():
    return load_krang()


def frictionless(robot):
    return drivetrain(
        robot,
        viscous_friction=0.0,
        ground_viscous=0.0,
        coulomb_friction=0.0,
        yaw_friction=0.0,
        caster_stiffness=0.0,
        caster_damping=0.0,
    )


def test_reduction_against_pinocchio_inertia_algebra(krang):
    """Body mass, CoM and inertia about the axle from pinocchio's spatial inertias (wheels
    excluded)."""
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    model = krang.model
    data = model.createData()
    pin.forwardKinematics(model, data, krang.pin_configuration(POSE))
    total = model.inertias[0].copy()  # Base, fixed to the universe
    wheel_joints = {model.getJointId('JLWheel'), model.getJointId('JRWheel')}
    for j in range(1, model.njoints):
        if j not in wheel_joints:
            total += data.oMi[j].act(model.inertias[j])
    assert body.mass == pytest.approx(total.mass, rel=1e-12)
    assert body.com_distance == pytest.approx(
        math.hypot(total.lever[1], total.lever[2]), rel=1e-12
    )
    # rotational inertia about the base origin: I_c + m (|c|^2 1 - c c^T); the axle is base x
    c = total.lever
    about_origin = total.inertia + total.mass * (c @ c * np.eye(3) - np.outer(c, c))
    assert body.inertia_axle == pytest.approx(about_origin[0, 0], rel=1e-12)


def test_balanced_pose_has_zero_com_angle(krang):
    beta = krang.nominal_beta
    q_base = balance_pitch(krang, POSE[None], beta)[0]
    body = reduce_pose(krang, POSE, beta)
    assert q_base + body.com_offset_full == pytest.approx(0.0, abs=1e-12)
    # the body alone (no wheels) is balanced at the same pitch when the wheels sit on the axle
    assert q_base + body.com_offset == pytest.approx(0.0, abs=1e-12)
    assert com_frame0(krang, [q_base], POSE[None], beta)[0, 2] > 0


def test_coulomb_friction_reacts_on_the_body_as_the_motor_torque_does(krang):
    """Wheel-to-body Coulomb friction is a torque between wheel and body: its accelerations are
    those of a motor torque of the same size and opposite sign (the motor's path is the
    reference), on the wheel and on the pitch."""
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    c = 4.0  # N m per wheel
    with_friction = WipDynamics(body, replace(frictionless(krang), coulomb_friction=c))
    reference = WipDynamics(body, frictionless(krang))
    for q_base, dphi, dq_base in ((-1.6, 2.0, 0.3), (-1.5, -1.0, 0.4), (-1.7, 0.05, 0.0)):
        rel = dphi - dq_base
        tau_friction = 2.0 * c * math.tanh(rel / 1e-2)
        got = with_friction.pitch_accelerations(q_base, dphi, dq_base, 0.0)
        want = reference.pitch_accelerations(q_base, dphi, dq_base, -tau_friction)
        assert got == pytest.approx(want, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize('make_robot', [load_krang, load_wip7])
def test_energy_is_conserved_without_friction_or_input(make_robot):
    robot = make_robot()
    pose = np.zeros(len(robot.pose_joints)) if robot.name == 'wip7' else POSE
    body = reduce_pose(robot, pose, robot.nominal_beta)
    dyn = WipDynamics(body, frictionless(robot))
    state = [
        0.0,
        -body.com_offset + 0.3,
        0.5,
        -0.2,
        0.0,
        0.3,
    ]  # falling from 0.3 rad, rolling, turning
    e0 = dyn.energy(state)
    for _ in range(4000):  # 0.4 s of a fall through large angles
        state = dyn.step_rk4(state, 0.0, 0.0, 1e-4)
    assert abs(dyn.energy(state) - e0) < 1e-7 * abs(e0) + 1e-6
    assert abs(state[1] - (-body.com_offset + 0.3)) > 0.1  # it really moved


def test_semi_implicit_euler_tracks_rk4(krang):
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    dyn = WipDynamics(body, drivetrain(krang))
    a = b = [0.0, -body.com_offset + 0.05, 0.0, 0.0, 0.0, 0.0]
    for _ in range(500):
        a = dyn.step(a, 5.0, 4.0, 1e-3)
        b = dyn.step_rk4(b, 5.0, 4.0, 1e-3)
    np.testing.assert_allclose(a, b, atol=5e-3)


def test_one_step_function_for_floats_and_batches(krang):
    """``step_pitch`` is the one integrator: ``step`` on floats and ``step_pitch`` on arrays of
    states and parameter sets (the replay's batches) give the same numbers, bit for bit."""
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    nominal = drivetrain(krang)
    drives = [
        replace(nominal, torque_constant=k, coulomb_friction=c)
        for k, c in ((0.08, 0.0), (0.07, 0.4))
    ]
    rng = np.random.default_rng(1)
    qb = -body.com_offset + rng.uniform(-0.2, 0.2, 5)
    phi, dphi, dqb = rng.normal(size=(3, 5))
    tau = rng.uniform(-20, 20, 5)
    batched = WipDynamics(body, stack(drives))
    out = batched.step_pitch(phi[None], qb[None], dphi[None], dqb[None], tau[None], 1e-3)
    for p, drive in enumerate(drives):
        dyn = WipDynamics(body, drive)
        for i in range(5):
            state = [float(phi[i]), float(qb[i]), float(dphi[i]), float(dqb[i]), 0.3, 0.1]
            one = dyn.step(state, 0.25 * float(tau[i]), 0.75 * float(tau[i]), 1e-3)
            assert [float(x[p, i]) for x in out] == one[:4]
            acc = dyn.accelerations(state, 0.25 * float(tau[i]), 0.75 * float(tau[i]))
            assert one[5] == state[5] + 1e-3 * acc[2] and one[4] == state[4] + 1e-3 * one[5]


def test_array_steps_leave_their_inputs_and_with_body_is_a_new_body(krang):
    """``step_pitch`` on arrays returns new arrays and leaves its inputs alone; ``with_body`` is
    the dynamics of a new body on the same drive train."""
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    drive = replace(drivetrain(krang), coulomb_friction=0.3, floor_slope=0.01, ground_viscous=0.2)
    rng = np.random.default_rng(4)
    state = [rng.normal(size=7), -body.com_offset + rng.uniform(-0.3, 0.3, 7)]
    state += [rng.normal(size=7), rng.normal(size=7)]
    state[1][:2] = drive.caster_contact_pitch - 0.01  # two on the caster
    tau = rng.uniform(-20, 20, 7)
    other = replace(body, com_distance=body.com_distance * 1.1, com_offset=body.com_offset + 0.01)
    copies = [x.copy() for x in state]
    stepped = WipDynamics(body, drive).step_pitch(*state, tau, 1e-3, 0.5, -0.5)
    assert all(np.array_equal(a, b) for a, b in zip(state, copies))
    assert not any(np.array_equal(a, b) for a, b in zip(stepped, state))
    moved = WipDynamics(body, drive).with_body(other)
    assert moved.body is other
    want = WipDynamics(other, drive).step_pitch(*state, tau, 1e-3)
    assert all(np.array_equal(a, b) for a, b in zip(moved.step_pitch(*state, tau, 1e-3), want))


def test_held_command_is_the_delay_of_a_stepping_plant():
    """HeldCommand: each value held until the next, `delay` later, zero before the first; its
    integral is exact for the held steps. A plant stepping at dt that applies the command sent
    command_delay_steps(delay, dt) steps earlier applies HeldCommand.applied during each step."""
    dt = 1e-3
    t = np.arange(50) * dt
    values = np.column_stack([np.sin(t * 90.0), np.cos(t * 70.0)])
    held = HeldCommand(t, values)
    delay = 0.0071
    n = command_delay_steps(delay, dt)
    assert n == 7
    queue = [(0.0, 0.0)] * n
    for k, tk in enumerate(t):
        queue.append(tuple(values[k]))
        assert tuple(held.applied(tk + 0.5 * dt, n * dt)) == queue.pop(0)  # during step k
    assert np.all(held.applied(t[:7] + 1e-9, delay) == 0.0)  # nothing before the first command
    # the integral's differences are the held values times the step, shifted by the delay
    edges = t[10:40] + 0.5 * dt
    means = np.diff(held.integral(edges, 0.003), axis=0) / dt
    np.testing.assert_allclose(means, 0.5 * (values[7:36] + values[8:37]), atol=1e-9)
    assert np.all(HeldCommand(np.zeros(0), np.zeros(0)).integral(edges) == 0.0)


def test_linearisation_matches_finite_differences(krang):
    body = reduce_pose(krang, POSE, krang.nominal_beta)
    drive = replace(drivetrain(krang), ground_viscous=0.3)
    dyn = WipDynamics(body, drive)
    a_lin, b_lin = linearize(body, drive)
    r = drive.wheel_radius
    upright = -body.com_offset

    def f(x, tau):
        # paper state [x, x', theta, theta'] -> ours [phi, q_base, phi', q_base', psi, psi']
        state = [x[0] / r, upright + x[2], x[1] / r, x[3], 0.0, 0.0]
        ddphi, ddqb, _ = dyn.accelerations(state, tau / 2, tau / 2)
        return np.array([x[1], r * ddphi, x[3], ddqb])

    h = 1e-6
    a_fd = np.column_stack([(f(h * e, 0.0) - f(-h * e, 0.0)) / (2 * h) for e in np.eye(4)])
    b_fd = (f(np.zeros(4), h) - f(np.zeros(4), -h)) / (2 * h)
    np.testing.assert_allclose(a_lin, a_fd, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(b_lin[:, 0], b_fd, rtol=1e-6, atol=1e-8)
    # an inverted pendulum: exactly one unstable open-loop pole
    assert sum(np.linalg.eigvals(a_lin).real > 1e-6) == 1


def test_caster_holds_the_sitting_robot(krang):
    sit_pose = TABLE2_POSE.copy()
    sit_pose[0] = (
        2.2  # waist: with beta_0 the Table II pose itself balances behind the caster (README)
    )
    body = reduce_pose(krang, sit_pose, krang.nominal_beta)
    assert -body.com_offset > -1.5  # upright balance well forward of the caster
    drive = drivetrain(krang)
    dyn = WipDynamics(body, drive)
    state = [0.0, drive.caster_pitch + 0.02, 0.0, 0.0, 0.0, 0.0]
    for _ in range(3000):
        state = dyn.step(state, 0.0, 0.0, 1e-3)
    assert state[1] == pytest.approx(drive.caster_pitch, abs=0.01)  # resting on the caster
    assert abs(state[3]) < 1e-3


def test_current_limit_and_torque_constant(krang):
    drive = drivetrain(krang)
    dyn = WipDynamics(reduce_pose(krang, POSE, krang.nominal_beta), drive)
    left, right = dyn.wheel_torques_from_currents(10.0, -1e6)
    assert left == pytest.approx(10.0 * 0.0847 * 15.0)
    assert right == pytest.approx(-49.0 * 0.0847 * 15.0)
