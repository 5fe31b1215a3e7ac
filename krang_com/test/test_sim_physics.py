"""The reduced plant and the sensor model: sensors consistent with the state, effects (the
registry's, as ModelTerms) doing what their names say."""

import math

import numpy as np
import pytest

from krang_model.com import balance_pitch
from krang_model.drivetrain import drivetrain
from krang_model.effects import ModelTerms, model_terms
from krang_model.robot import load_krang
from krang_sim.plant import UnsupportedTerm, make_plant, terms_from_strings
from krang_sim.reduced_plant import ReducedPlant
from krang_sim.sensors import CommandDelay, SensorModel, SensorNoise, quiet_noise
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
QUIET = quiet_noise()


@pytest.fixture(scope='module')
def krang():
    return load_krang()


def terms(krang, **effects):
    """The true robot with these effects of the registry (keys with '@' as '__')."""
    effects = {k.replace('__', '@'): v for k, v in effects.items()}
    return model_terms(effects, ModelTerms.nominal(drivetrain(krang)))


def sim(krang, q_base=None, **effects):
    plant = ReducedPlant(
        krang, krang.nominal_beta, POSE, q_base=q_base, terms=terms(krang, **effects)
    )
    plant.sensor_model = SensorModel(krang, plant.terms, QUIET)
    return plant


def read(plant):
    """Every device's reading of the plant now."""
    return plant.sensor_model.sample(plant.motion())


def test_sitting_robot_rests_on_the_caster_and_the_accelerometer_sees_the_pitch(krang):
    s = sim(krang)
    s.step(3000)
    read_ = read(s)
    assert read_.q_base == pytest.approx(s.drive.caster_pitch, abs=0.01)
    f = read_.specific_force
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
    a, b = sim(krang), sim(krang, imu_pitch_bias=0.01)
    a.step(500)
    b.step(500)
    assert b.q_base == pytest.approx(a.q_base, abs=1e-12)
    assert read(b).q_base - read(a).q_base == pytest.approx(0.01, abs=1e-9)
    fa, fb = read(a).specific_force, read(b).specific_force
    assert math.atan2(fb[2], fb[1]) - math.atan2(fa[2], fa[1]) == pytest.approx(0.01, abs=1e-3)


def test_payload_moves_the_true_balance(krang):
    heavy = sim(krang, payload__lGripper=2.0)
    expected = balance_pitch(krang, POSE[None], heavy.true_beta)[0]
    assert heavy.balance_pitch() == pytest.approx(expected, abs=1e-12)
    assert abs(heavy.balance_pitch() - sim(krang).balance_pitch()) > 1e-3
    assert heavy.true_beta[0::4].sum() == pytest.approx(krang.nominal_mass + 2.0)


def test_torque_constant_delay_and_current_limit(krang):
    free, a, b = (
        sim(krang, q_base=-1.0),
        sim(krang, q_base=-1.0),
        sim(krang, q_base=-1.0, torque_constant=0.5),
    )
    for s in (a, b):
        s.command_currents(20.0, 20.0)
    for s in (free, a, b):
        s.step(5)
    # the wheel acceleration due to the motors is linear in the torque: half Kt, half the effect
    assert b.state[2] - free.state[2] == pytest.approx(
        0.5 * (a.state[2] - free.state[2]), rel=1e-3
    )
    d = sim(krang, q_base=-1.0, actuation_delay=0.01)
    d.command_currents(100.0, -100.0)
    d.step(9)
    assert d.applied_current == (0.0, 0.0)
    d.step(2)
    assert d.applied_current == (49.0, -49.0)  # clamped at the drive limit


def test_encoder_offset_and_joint_speed_limits(krang):
    s = sim(krang, encoder_offset=0.02)
    assert read(s).joints[0] - POSE[0] == pytest.approx(0.02)
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
    """The physical effects of the registry become the true robot's Drivetrain, which
    krang_model.wip integrates: the plant steps with the drive train of its terms."""
    nominal = drivetrain(krang)
    plant = sim(
        krang,
        floor_slope=0.01,
        wheel_radius=0.25,
        wheel_viscous_friction=2.0,
        wheel_coulomb_friction=0.5,
        torque_constant=0.8,
        rolling_resistance=1.5,
    )
    d = plant.drive
    assert d is plant.terms.drive and plant.dynamics.drive is d
    assert (d.floor_slope, d.wheel_radius) == (0.01, 0.25)
    assert d.viscous_friction == pytest.approx(nominal.viscous_friction + 2.0)
    assert d.coulomb_friction == pytest.approx(nominal.coulomb_friction + 0.5)
    assert d.ground_viscous == pytest.approx(nominal.ground_viscous + 1.5)
    assert d.torque_constant == pytest.approx(0.8 * nominal.torque_constant)
    assert sim(krang).drive == nominal
    slow = sim(krang, q_base=-1.0, rolling_resistance=50.0)
    free = sim(krang, q_base=-1.0)
    for s in (slow, free):
        s.state[2] = 1.0  # rolling forward
        s.step(50)
    assert slow.state[2] < free.state[2] - 0.05  # the rolling resistance brakes the wheels


def test_sensor_resolutions_are_the_device_maps_and_the_dbcs():
    """The sensor model's resolutions are the ones the bridge decodes with: the encoder counts of
    the device map, the DMU's LSBs of its DBC."""
    from krang_can_bridge.config import load_devices
    from krang_can_bridge.protocols import load_dbc
    from krang_can_bridge.protocols.dmu_imu import DmuCodec

    devices = load_devices()
    dmu = DmuCodec(load_dbc(devices.dbc_path))
    noise = SensorNoise()
    assert noise.encoder_counts_per_rad == devices.wheels.counts_per_wheel_rad
    assert noise.gyro_lsb_rad_s == dmu.rate_lsb_rad_s
    assert noise.accel_lsb_m_s2 == dmu.accel_lsb_m_s2


def test_terms_the_reduced_plant_cannot_take_and_the_extra_forces_it_can(krang):
    """An extra generalised force of the terms acts on the plant (a spring on the pitch holds the
    body up); a plant name nobody registered is refused with the known ones."""
    spring = ModelTerms.nominal(drivetrain(krang))
    spring.extra_forces.append(lambda s: (0.0 * s.q_base, -2000.0 * (s.q_base + 1.3)))
    free = ReducedPlant(krang, krang.nominal_beta, POSE, q_base=-1.3)
    held = ReducedPlant(krang, krang.nominal_beta, POSE, q_base=-1.3, terms=spring)
    free.push(0.5)
    held.push(0.5)
    free.step(800)
    held.step(800)
    assert abs(held.q_base + 1.3) < 0.1 and free.q_base > -0.5  # held / fallen forward
    with pytest.raises(ValueError, match='reduced'):
        make_plant('no-such-engine', krang, krang.nominal_beta, POSE)
    assert issubclass(UnsupportedTerm, ValueError)


def test_effects_from_strings_and_the_command_delay(krang):
    """'key=value' strings (sim_krang's `effects` parameter) name the registry's effects; the
    command delay applies each command whole steps later, zero before."""
    t = terms_from_strings(
        krang, ['torque_constant=0.5', 'payload@rGripper=2', 'imu_pitch_bias=0.01']
    )
    assert t.drive.torque_constant == pytest.approx(0.5 * drivetrain(krang).torque_constant)
    assert t.payloads[0][0] == 'rGripper' and t.imu_pitch_bias == 0.01
    with pytest.raises(ValueError):
        terms_from_strings(krang, ['torque_constant'])
    delay = CommandDelay(0.003, 1e-3)
    assert [delay.push(k) for k in (1, 2, 3, 4, 5)] == [(0.0, 0.0)] * 3 + [1, 2]
    assert CommandDelay(0.0, 1e-3).push(7) == 7


class _AlwaysRecomputed(ReducedPlant):
    """The second implementation: _move_joints never takes its at-rest shortcut."""

    def _move_joints(self, dt):
        self._still = False
        super()._move_joints(dt)


@pytest.mark.parametrize('seed', [3, 11, 29])
def test_a_robot_at_rest_skips_only_work_that_changes_nothing(krang, monkeypatch, seed):
    """The at-rest shortcut of _move_joints (most of a balancing session's steps) gives the same
    states, bit for bit, as the full step, through moves, arrivals and holds."""
    import krang_sim.reduced_plant as reduced_plant

    reductions = []
    real_reduce = reduced_plant.reduce_pose
    monkeypatch.setattr(
        reduced_plant, 'reduce_pose', lambda *a: reductions.append(1) or real_reduce(*a)
    )
    fast, full = (
        sim(krang, q_base=0.0),
        _AlwaysRecomputed(krang, krang.nominal_beta, POSE, q_base=0.0),
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
