"""The simulated robot: sensors consistent with the state, effects doing what their names say."""

import math

import numpy as np
import pytest

from krang_model.com import balance_pitch
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_sim.physics import KrangSim, SimConfig, SimEffects, SensorNoise
from krang_sim.truths import perturbed_beta

POSE = np.array(
    [
        2.2,
        0.0749,
        1.008,
        -1.113,
        0.0,
        -1.594,
        0.037,
        1.022,
        -0.021,
        -0.855,
        1.113,
        0.0,
        1.561,
        -0.028,
        -1.052,
        0.021,
    ]
)
QUIET = SensorNoise(
    imu_pitch_std_rad=0.0, gyro_std_rad_s=0.0, accel_std_m_s2=0.0, joint_std_rad=0.0
)


@pytest.fixture(scope='module')
def krang():
    return load_krang()


def sim(krang, q_base=None, **effects):
    return KrangSim(
        krang,
        krang.nominal_beta,
        POSE,
        q_base=q_base,
        config=SimConfig(effects=SimEffects(**effects), noise=QUIET),
    )


def test_sitting_robot_rests_on_the_caster_and_the_accelerometer_sees_the_pitch(krang):
    s = sim(krang)
    s.step(3000)
    read = s.sensors()
    assert read.q_base == pytest.approx(s.drive.caster_pitch, abs=0.01)
    f = read.specific_force
    assert math.hypot(f[1], f[2]) == pytest.approx(9.81, abs=0.01)
    assert math.atan2(f[2], f[1]) == pytest.approx(s.q_base, abs=1e-3)


def test_balance_pitch_is_the_model_balance_and_the_body_falls_away_from_it(krang):
    s = sim(krang)
    qb = balance_pitch(krang, POSE[None], krang.nominal_beta)[0]
    assert s.balance_pitch() == pytest.approx(qb, abs=1e-12)
    s.state[1] = qb + 0.02
    s.step(600)
    assert s.q_base > qb + 0.05  # unstable (pole near +3 rad/s): falls forward


def test_imu_bias_shifts_the_reading_not_the_robot(krang):
    a, b = sim(krang), sim(krang, imu_pitch_bias_rad=0.01)
    a.step(500)
    b.step(500)
    assert b.q_base == pytest.approx(a.q_base, abs=1e-12)
    assert b.sensors().q_base - a.sensors().q_base == pytest.approx(0.01, abs=1e-9)
    fa, fb = a.sensors().specific_force, b.sensors().specific_force
    assert math.atan2(fb[2], fb[1]) - math.atan2(fa[2], fa[1]) == pytest.approx(0.01, abs=1e-3)


def test_payload_moves_the_true_balance(krang):
    heavy = sim(krang, payload_kg=2.0, payload_body='lGripper')
    expected = balance_pitch(krang, POSE[None], heavy.true_beta)[0]
    assert heavy.balance_pitch() == pytest.approx(expected, abs=1e-12)
    assert abs(heavy.balance_pitch() - sim(krang).balance_pitch()) > 1e-3
    assert heavy.true_beta[0::4].sum() == pytest.approx(krang.nominal_mass + 2.0)


def test_torque_constant_delay_and_current_limit(krang):
    free, a, b = (
        sim(krang, q_base=-1.0),
        sim(krang, q_base=-1.0),
        sim(krang, q_base=-1.0, torque_constant_scale=0.5),
    )
    for s in (a, b):
        s.command_currents(20.0, 20.0)
    for s in (free, a, b):
        s.step(5)
    # the wheel acceleration due to the motors is linear in the torque: half Kt, half the effect
    assert b.state[2] - free.state[2] == pytest.approx(
        0.5 * (a.state[2] - free.state[2]), rel=1e-3
    )
    d = sim(krang, q_base=-1.0, actuation_delay_s=0.01)
    d.command_currents(100.0, -100.0)
    d.step(9)
    assert d.applied_current == (0.0, 0.0)
    d.step(2)
    assert d.applied_current == (49.0, -49.0)  # clamped at the drive limit


def test_encoder_offset_and_joint_speed_limits(krang):
    s = sim(krang, encoder_offset_rad=0.02)
    assert s.sensors().joints[0] - POSE[0] == pytest.approx(0.02)
    target = POSE.copy()
    target[1] += 1.0  # torso, 0.436 rad/s
    s.command_joints(target)
    s.step(1000)
    assert s.joints[1] - POSE[1] == pytest.approx(0.436, abs=1e-6)
    assert s.joints_moving
    s.step(2000)
    assert not s.joints_moving


def test_perturbed_truth_is_physical(krang):
    beta = perturbed_beta(krang, seed=3)
    assert beta[0::4].sum() == pytest.approx(krang.nominal_mass)
    assert np.all(beta[0::4] > 0)
    for w in krang.wheel_body_ids:
        assert np.all(beta[4 * w + 1 : 4 * w + 4] == 0)


def test_effects_are_values_of_the_true_drive_train(krang):
    """The physical effects become the true robot's Drivetrain, which krang_model.wip integrates;
    drive_extra adds to any of its fields (a new term needs no simulator code)."""
    nominal = drivetrain(krang)
    fx = SimEffects(
        floor_slope_rad=0.01,
        wheel_radius_m=0.25,
        wheel_viscous_Nm_s=2.0,
        wheel_coulomb_Nm=0.5,
        torque_constant_scale=0.8,
        drive_extra={'ground_viscous': 1.5, 'viscous_friction': 0.25},
    )
    d = fx.drive(krang)
    assert (d.floor_slope, d.wheel_radius) == (0.01, 0.25)
    assert d.viscous_friction == pytest.approx(nominal.viscous_friction + 2.25)
    assert d.coulomb_friction == pytest.approx(nominal.coulomb_friction + 0.5)
    assert d.ground_viscous == pytest.approx(nominal.ground_viscous + 1.5)
    assert d.torque_constant == pytest.approx(0.8 * nominal.torque_constant)
    assert SimEffects().drive(krang) == nominal
    slow = sim(krang, q_base=-1.0, drive_extra={'ground_viscous': 50.0})
    free = sim(krang, q_base=-1.0)
    for s in (slow, free):
        s.state[2] = 1.0  # rolling forward
        s.step(50)
    assert slow.state[2] < free.state[2] - 0.05  # the rolling resistance brakes the wheels


def test_simulated_encoder_resolution_is_the_device_maps():
    """The simulator's default encoder resolution is the one the bridge decodes with."""
    from krang_can_bridge.config import load_devices
    from krang_sim.physics import SensorNoise

    wheels = load_devices().wheels
    assert SensorNoise().encoder_counts_per_rad == pytest.approx(wheels.counts_per_wheel_rad)


class _AlwaysRecomputed(KrangSim):
    """The second implementation: _move_joints never takes its at-rest shortcut."""

    def _move_joints(self, dt):
        self._still = False
        super()._move_joints(dt)


@pytest.mark.parametrize('seed', [3, 11, 29])
def test_a_robot_at_rest_skips_only_work_that_changes_nothing(krang, monkeypatch, seed):
    """The at-rest shortcut of _move_joints (most of a balancing session's steps) gives the same
    states, bit for bit, as the full step, through moves, arrivals and holds."""
    import krang_sim.physics as physics

    reductions = []
    real_reduce = physics.reduce_pose
    monkeypatch.setattr(physics, 'reduce_pose', lambda *a: reductions.append(1) or real_reduce(*a))
    fast, full = (
        sim(krang, q_base=0.0),
        _AlwaysRecomputed(
            krang, krang.nominal_beta, POSE, q_base=0.0, config=SimConfig(noise=QUIET)
        ),
    )
    rng = np.random.default_rng(seed)
    targets, still_steps = POSE.copy(), 0
    for phase in range(6):
        if phase % 2:  # a new target for a few joints, then hold it
            joints = rng.choice(len(POSE), 3, replace=False)
            targets = targets.copy()
            targets[joints] += rng.uniform(-0.05, 0.05, 3)
        for _ in range(300):
            current = 2.0 * math.sin(10.0 * fast.t)
            for s in (fast, full):
                s.command_joints(targets)
                s.command_currents(current, -current)
                s.step()
            still_steps += fast._still
            assert fast.state == full.state
            assert np.array_equal(fast.joints, full.joints)
            assert fast.balance_pitch() == full.balance_pitch()
    assert still_steps > 600  # the shortcut was taken, on most of the holds
    before = len(reductions)
    fast.step(100)
    assert len(reductions) == before  # and it reduces nothing at rest
