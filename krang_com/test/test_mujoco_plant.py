"""The full-body MuJoCo plant against physics stated independently of it: the URDF's mass, the
documented sitting pitch, rolling without slip, torque and friction laws, the modules' speed
limits, conservation of momentum while the arms move, and krang_model's balance pitch."""

from dataclasses import replace

import numpy as np
import pytest

mujoco = pytest.importorskip(
    'mujoco', reason='the MuJoCo plant needs the optional `mujoco` package'
)

from krang_model.beta import load_beta  # noqa: E402
from krang_model.com import balance_pitch, com_frame0  # noqa: E402
from krang_model.config import config_path  # noqa: E402
from krang_model.drivetrain import drivetrain  # noqa: E402
from krang_model.effects import ModelTerms  # noqa: E402
from krang_model.robot import load_krang  # noqa: E402
from krang_sim.mujoco_plant import ARRIVED_RAD, MujocoPlant  # noqa: E402
from krang_sim.plant import UnsupportedTerm, make_plant  # noqa: E402

#: the upper-body pose of the paper's Table II runs, where the simulated truth sits on its caster
TABLE2_POSE = np.array(
    [2.75467, 0.0749392, 1.00799, -1.113, -0.000251086, -1.59399, 0.0370958, 1.02202]
    + [-0.0209895, -0.854931, 1.113, 0.000271173, 1.561, -0.0280979, -1.052, 0.0210068]
)
SITTING_PITCH = -1.7628  # krang_model/README.md, config/robot.yaml


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def truth(robot):
    """The simulator's hidden truth (fitted to the real balanced poses): it sits on the caster
    in the Table II pose (beta_0 would balance behind the caster there)."""
    return load_beta(config_path('sim_true_beta.yaml'), robot)


def plant(robot, beta, joints=TABLE2_POSE, drive=None, settle_s=0.5, **kw):
    terms = None if drive is None else ModelTerms.nominal(drive)
    p = make_plant('mujoco', robot, beta, joints, terms=terms, **kw)
    p.step(int(settle_s / p.dt))
    return p


def travel(p, left_a, right_a, seconds):
    """Drive both wheels for `seconds`: (axle travel along the floor, ground-referenced wheel
    angle x radius) in m."""
    m0, x0 = p.motion(), p.truth()
    p.command_currents(left_a, right_a)
    p.step(int(round(seconds / p.dt)))
    p.command_currents(0.0, 0.0)
    m1, x1 = p.motion(), p.truth()
    rel = 0.5 * (m1.wheel_left + m1.wheel_right - m0.wheel_left - m0.wheel_right)
    wheel = rel + (m1.q_base - m0.q_base)  # relative angle + body pitch = angle against ground
    return x1.x_m - x0.x_m, wheel * p.drive.wheel_radius


def test_registered_and_mass_of_the_urdf(robot):
    p = make_plant('mujoco', robot, robot.nominal_beta, np.zeros(16))
    assert isinstance(p, MujocoPlant)
    assert p.model.nbody == 26  # the world and the URDF's 25 links: the Base is not fused away
    assert p.total_mass() == pytest.approx(162.158, abs=1e-9)


def test_true_beta_sets_masses_and_coms(robot, truth):
    p = make_plant('mujoco', robot, truth, TABLE2_POSE)
    b4 = truth.reshape(-1, 4)
    for i, name in enumerate(robot.body_names):
        body = p.model.body(name)
        assert body.mass[0] == pytest.approx(b4[i, 0])
        assert body.ipos == pytest.approx(b4[i, 1:] / b4[i, 0], abs=1e-12)


def test_sits_at_the_documented_pitch(robot, truth):
    p = plant(robot, truth, settle_s=1.0)
    m, t = p.motion(), p.truth()
    assert m.q_base == pytest.approx(SITTING_PITCH, abs=1e-3)  # contact sag < 1 mrad
    assert abs(t.x_m) < 1e-4 and abs(m.dq_base) < 1e-3
    # the IMU at rest feels gravity only: |f| = g, and its direction gives the pitch
    f = np.array(m.specific_force)
    assert np.linalg.norm(f) == pytest.approx(9.81, abs=0.01)
    assert np.arctan2(f[2], f[1]) == pytest.approx(m.q_base, abs=2e-3)


def test_pitch_convention_matches_the_reduced_model(robot, truth):
    """Both plants start from the same sitting state and report it the same way."""
    mj = make_plant('mujoco', robot, truth, TABLE2_POSE)
    red = make_plant('reduced', robot, truth, TABLE2_POSE)
    a, b = mj.motion(), red.motion()
    assert a.q_base == pytest.approx(b.q_base, abs=1e-3)
    assert a.wheel_left == pytest.approx(b.wheel_left, abs=1e-3)
    assert mj.truth().balance_pitch == pytest.approx(red.truth().balance_pitch, abs=1e-9)


def test_wheels_roll_without_creep(robot, truth):
    """10 A on both wheels for 0.5 s: the axle travels wheel angle x radius (slip < 0.1 mm),
    as far as the notes' trial found (71.7 mm), and the caster does not hold it back."""
    p = plant(robot, truth)
    x, rolled = travel(p, 10.0, 10.0, 0.5)
    assert x == pytest.approx(0.0717, abs=0.002)
    assert abs(x - rolled) < 1e-4
    assert p.motion().applied_current == (0.0, 0.0)


def test_current_limit_clamps(robot, truth):
    p = plant(robot, truth, settle_s=0.0)
    p.command_currents(500.0, -500.0)
    lim = p.drive.current_limit
    assert p.motion().applied_current == (lim, -lim)


def test_an_actuation_delay_applies_each_current_that_much_later(robot, truth):
    """The drives' delay stands in front of this plant as of every plant: a delayed plant under a
    current sequence moves exactly as an undelayed one under the same sequence started 20 steps
    later (20 ms at 1 ms steps)."""
    rng = np.random.default_rng(3)
    currents = rng.uniform(-12.0, 12.0, size=(60, 2))
    delayed = make_plant(
        'mujoco',
        robot,
        truth,
        TABLE2_POSE,
        terms=replace(ModelTerms.nominal(drivetrain(robot)), actuation_delay=0.02),
    )
    shifted = make_plant('mujoco', robot, truth, TABLE2_POSE)
    for k, (left, right) in enumerate(currents):
        delayed.command_currents(left, right)
        shifted.command_currents(*(currents[k - 20] if k >= 20 else (0.0, 0.0)))
        delayed.step(1)
        shifted.step(1)
        assert delayed.motion().applied_current == shifted.motion().applied_current
    assert np.array_equal(delayed.data.qpos, shifted.data.qpos)
    assert np.abs(delayed.data.qvel).max() > 0.0  # the currents did move the robot


def test_torque_constant_scales_the_push(robot, truth):
    """On the caster the robot is a cart under the wheel torque: travel is proportional to Kt."""
    nominal = drivetrain(robot)
    x1, _ = travel(plant(robot, truth), 10.0, 10.0, 0.5)
    weak = replace(nominal, torque_constant=0.6 * nominal.torque_constant)
    x06, _ = travel(plant(robot, truth, drive=weak), 10.0, 10.0, 0.5)
    assert x06 / x1 == pytest.approx(0.6, abs=0.01)


def test_coulomb_friction_holds_below_breakaway_and_subtracts_above(robot, truth):
    """Dry wheel friction c per wheel: a motor torque below c does not move the robot at all
    (static friction, no creep), one above moves it as if the torque were tau - c."""
    nominal = drivetrain(robot)
    k = nominal.torque_constant * nominal.gear_ratio  # N m per A at the wheel
    c = 4.0
    dry = replace(nominal, coulomb_friction=c)
    held, _ = travel(plant(robot, truth, drive=dry), 0.8 * c / k, 0.8 * c / k, 1.0)
    assert abs(held) < 2e-4  # creep of the regularised friction: 0.06 mm in 1 s
    x_free, _ = travel(plant(robot, truth), 10.0, 10.0, 0.5)
    x_dry, _ = travel(plant(robot, truth, drive=dry), 10.0, 10.0, 0.5)
    assert x_dry / x_free == pytest.approx((10.0 * k - c) / (10.0 * k), abs=0.02)


def test_unsupported_terms_are_refused(robot, truth):
    terms = ModelTerms.nominal(drivetrain(robot))
    terms.extra_forces.append(lambda s: (0.0, 0.0))
    with pytest.raises(UnsupportedTerm):
        make_plant('mujoco', robot, truth, TABLE2_POSE, terms=terms)
    terms = ModelTerms.nominal(drivetrain(robot))
    terms.com_shift = 0.01
    with pytest.raises(UnsupportedTerm):
        make_plant('mujoco', robot, truth, TABLE2_POSE, terms=terms)


def test_payload_adds_its_mass(robot, truth):
    terms = ModelTerms.nominal(drivetrain(robot))
    terms.payloads = (('lGripper', (0.0, 0.0, 0.1), 2.0),)
    p = make_plant('mujoco', robot, truth, TABLE2_POSE, terms=terms)
    assert p.total_mass() == pytest.approx(truth[0::4].sum() + 2.0)
    assert p.rest_balance_pitch(TABLE2_POSE)[0] == pytest.approx(p.truth().balance_pitch, abs=1e-9)


def test_floor_slope_tilts_the_sitting_pitch(robot, truth):
    """A floor rising forward by alpha tilts the sitting robot back by alpha against gravity
    (Drivetrain.caster_contact_pitch)."""
    slope = 0.05
    drive = replace(drivetrain(robot), floor_slope=slope)
    p = plant(robot, truth, drive=drive, settle_s=0.0)
    p.command_currents(0.0, 0.0)
    q0 = p.motion().q_base
    assert q0 == pytest.approx(SITTING_PITCH - slope, abs=1e-3)
    # with no wheel torque it rolls back down the slope
    p.step(500)
    assert p.truth().x_m < -0.01


def test_arms_move_at_module_speed_and_push_the_base(robot, truth):
    """The modules never exceed their speed limits, arrive at the target, and the arms' momentum
    acts on the body: with the wheels free and a frictionless caster no horizontal force acts
    on the robot, so its CoM stays put while the body rolls under it."""
    p = plant(robot, truth, settle_s=0.3)

    def com_x():
        t = p.truth()
        return t.x_m + com_frame0(robot, t.q_base, p.joints[None], p.true_beta)[0, 0]

    c0, x0 = com_x(), p.truth().x_m
    target = TABLE2_POSE.copy()
    target[0] -= 0.4  # waist
    target[3] += 0.6  # left shoulder
    target[10] -= 0.6  # right shoulder
    p.command_joints(target)
    assert p.joints_moving
    peak = np.zeros(16)
    while p.joints_moving and p.t < 5.0:
        p.step(2)
        peak = np.maximum(peak, np.abs(p.joint_rates))
    assert not p.joints_moving
    assert np.all(peak <= 1.03 * robot.velocity_limit)
    assert peak[0] > 0.95 * robot.velocity_limit[0]  # it did reach the waist's speed
    assert np.allclose(p.joints, target, atol=ARRIVED_RAD)  # arrived: within ARRIVED_RAD
    p.step(500)  # and the servos settle on the target
    assert np.allclose(p.joints, target, atol=2e-4)
    moved = p.truth().x_m - x0
    assert abs(moved) > 0.05  # the body rolled back while the upper body leaned forward
    assert abs(com_x() - c0) < 0.05 * abs(moved)  # wheel spin inertia and friction: a few %


def test_push_turns_the_body_about_the_axle(robot, truth):
    p = plant(robot, truth, settle_s=0.0)
    before = p.motion()
    p.push(0.2)
    after = p.motion()
    assert after.dq_base - before.dq_base == pytest.approx(0.2)
    # the wheels keep their spin against the ground
    assert after.wheel_left_rate - before.wheel_left_rate == pytest.approx(-0.2)


def _safe_poses(n, seed, beta):
    """Poses of the pose pool: no self-collision, nothing below the floor at the balance pitch
    of `beta`."""
    pool = pytest.importorskip('krang_pose_server.pool')
    return pool.generate_pool(n, seed=seed, real_beta=beta).joints


@pytest.mark.parametrize('n', [1000])
def test_rest_balance_pitch_agrees_with_krang_model(robot, truth, n):
    """At rest, MuJoCo's balance pitch (the zero of its own gravity torque about the axle, from
    its parse of the URDF) equals krang_model's CoM-over-the-axle pitch, for safe poses. 1000
    poses take 0.2 s, so the full check is in the default run."""
    for beta in (robot.nominal_beta, truth):
        joints = _safe_poses(n, 35, beta)
        p = make_plant('mujoco', robot, beta, joints[0])
        mj = p.rest_balance_pitch(joints)
        assert np.max(np.abs(mj - balance_pitch(robot, joints, beta))) < 1e-9


def _free_fall_side(p, joints, pitch, seconds=0.3):
    """Start on the wheels at `pitch`, at rest, wheels unpowered: +1 if the body falls forward."""
    p.reset(joints, pitch)
    p.step(int(seconds / p.dt))
    return np.sign(p.truth().q_base - pitch)


def _bracket(robot, truth, n, delta=2e-3):
    joints = _safe_poses(n, 36, truth)
    p = make_plant('mujoco', robot, truth, joints[0])
    q = balance_pitch(robot, joints, truth)
    for pose, qb in zip(joints, q):
        assert _free_fall_side(p, pose, qb + delta) == 1
        assert _free_fall_side(p, pose, qb - delta) == -1


def test_balance_pitch_brackets_the_free_fall(robot, truth):
    """The full dynamics on the wheels agree too: started 2 mrad ahead of krang_model's balance
    pitch the robot falls forward, 2 mrad behind it falls back (20 poses)."""
    _bracket(robot, truth, 20)


@pytest.mark.slow
def test_balance_pitch_brackets_the_free_fall_1000_poses(robot, truth):
    _bracket(robot, truth, 1000)


def test_turning_follows_wheel_odometry_and_the_gyro(robot, truth):
    """Opposite currents turn the robot in place (left wheel back: a left turn, yaw > 0, as the
    reduced model has it); the yaw is what rolling without slip gives, r (dR - dL) / track, and
    the gyro sees the yaw rate in the Base frame as (0, cos q, sin q) psi'."""
    p = plant(robot, truth, settle_s=0.3)
    m0 = p.motion()
    p.command_currents(-8.0, 8.0)
    p.step(800)
    m1, t = p.motion(), p.truth()
    r, track = p.drive.wheel_radius, p.drive.track_width
    odometry = r * ((m1.wheel_right - m0.wheel_right) - (m1.wheel_left - m0.wheel_left)) / track
    assert t.yaw > 0.3
    assert t.yaw == pytest.approx(odometry, rel=0.01)
    assert abs(t.x_m) < 0.005
    dpsi = t.state[5]
    assert m1.gyro[1] == pytest.approx(dpsi * np.cos(m1.q_base), abs=1e-3)
    assert m1.gyro[2] == pytest.approx(dpsi * np.sin(m1.q_base), abs=1e-3)


def test_rolling_resistance_brakes_the_coasting_robot(robot, truth):
    """Rolling resistance b (N m s, both wheels, on the wheels' spin against the floor) slows a
    robot coasting on its caster as exp(-b t / J), J = M r^2 + wheel and rotor inertia."""
    b = 20.0
    drive = replace(drivetrain(robot), ground_viscous=b)
    p = plant(robot, truth, drive=drive, settle_s=0.3)
    p.command_currents(15.0, 15.0)
    p.step(300)
    p.command_currents(0.0, 0.0)
    v0 = p.truth().state[2]
    p.step(300)
    v1 = p.truth().state[2]
    d = p.drive
    j = truth[0::4].sum() * d.wheel_radius**2 + d.wheel_inertia + d.reflected_rotor_inertia
    assert v1 / v0 == pytest.approx(np.exp(-b * 0.3 / j), rel=0.03)


def test_inertia_add_is_about_the_axle(robot, truth):
    terms = ModelTerms.nominal(drivetrain(robot))
    terms.inertia_add = 2.0
    heavy = make_plant('mujoco', robot, truth, TABLE2_POSE, terms=terms)
    plain = make_plant('mujoco', robot, truth, TABLE2_POSE)

    def base_ixx(p):
        m = p.model
        body = m.body('Base').id
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.body_iquat[body])
        rot = rot.reshape(3, 3)
        return (rot @ np.diag(m.body_inertia[body]) @ rot.T)[0, 0]

    assert base_ixx(heavy) - base_ixx(plain) == pytest.approx(2.0)


def test_set_true_beta_keeps_the_state(robot, truth):
    p = plant(robot, truth, settle_s=0.2)
    p.command_currents(5.0, 5.0)
    p.step(100)
    before = p.truth()
    heavier = truth.copy()
    heavier[0] += 10.0  # 10 kg more on the Base, at its origin (the axle)
    p.set_true_beta(heavier)
    after = p.truth()
    assert p.total_mass() == pytest.approx(truth[0::4].sum() + 10.0)
    assert after.state == pytest.approx(before.state)
    p.step(100)  # and it runs on from there
    assert p.truth().x_m > after.x_m
