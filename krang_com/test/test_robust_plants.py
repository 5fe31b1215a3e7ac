"""The loop on physics that is not the controller's model: the true robot from an extended model
(--plant-model) on either plant, the drive chains of real gearmotors (torque 0.6-0.8 of the
commanded, 2-8 N m of dry and up to 8 N m s of viscous friction per wheel), the detector's
stationary window, the controller's drive-chain parameters, the path check of pose moves, and the
campaign across plants and chains (krang_experiments.campaign).

The wheel travel per move this must show: the wheels' largest excursion from where a move began,
until its balanced point, stays under ``campaign.TRAVEL_LIMIT_M`` (1.5 m) on every chain."""

import math

import numpy as np
import pytest
import yaml

from krang_adrc_controller.adrc import drive_chain_overrides
from krang_adrc_controller.controller import BalanceController, load_controller_config
from krang_adrc_controller.detector import BalancedPoseDetector, DetectorConfig
from krang_cli.main import build_parser
from krang_discrepancy.extended_model import FORMAT
from krang_experiments import campaign
from krang_model.com import balance_pitch
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_pose_server.pool import PosePool
from krang_pose_server.selection import AdaptiveSelector
from krang_sim.plant import plant_terms, terms_from_strings
from krang_sim.scenarios import run_balance


@pytest.fixture(scope='module')
def robot():
    return load_krang()


def _extended_model(path):
    doc = {
        'format': FORMAT,
        'nominal': {'beta': ''},
        'effects': [
            {'effect': 'torque_constant', 'key': 'torque_constant', 'parameter': 0.58},
            {'effect': 'wheel_coulomb_friction', 'key': 'wheel_coulomb_friction', 'parameter': 8},
        ],
    }
    path.write_text(yaml.safe_dump(doc))
    return path


def test_plant_terms_take_an_extended_model_and_effects_on_top(robot, tmp_path):
    nominal = drivetrain(robot)
    model = _extended_model(tmp_path / 'extended_model.yaml')
    terms = plant_terms(robot, (), str(model))
    assert terms.drive.torque_constant == pytest.approx(0.58 * nominal.torque_constant)
    assert terms.drive.coulomb_friction == pytest.approx(8.0)
    more = plant_terms(robot, ['wheel_viscous_friction=3'], str(model))
    assert more.drive.viscous_friction == pytest.approx(nominal.viscous_friction + 3.0)
    assert more.drive.coulomb_friction == pytest.approx(8.0)
    same = plant_terms(robot, ['torque_constant=0.75'], None)
    assert same == terms_from_strings(robot, ['torque_constant=0.75'])
    bad = tmp_path / 'bad.yaml'
    bad.write_text('a: 1\n')
    with pytest.raises(ValueError, match='not an extended-model file'):
        plant_terms(robot, (), str(bad))


def test_the_commands_take_the_plant_and_its_model(tmp_path):
    parser = build_parser()
    args = parser.parse_args(
        ['experiment', 'many-truths', '--plant', 'mujoco', '--plant-model', 'm.yaml',
         '--effects', 'torque_constant=0.7', 'wheel_coulomb_friction=5']
    )  # fmt: skip
    assert (args.plant, args.plant_model) == ('mujoco', 'm.yaml')
    assert args.effects == ['torque_constant=0.7', 'wheel_coulomb_friction=5']
    for flag in ('--plant-model', '--extended-model'):  # the older name still works
        args = parser.parse_args(['experiment', 'table2', flag, 'm.yaml', '--plant', 'mujoco'])
        assert (args.plant_model, args.plant) == ('m.yaml', 'mujoco')
    demo = ['demo', '--plant', 'mujoco', '--plant-model', 'm.yaml']
    args = parser.parse_args([*demo, '--effects', 'torque_constant=0.7'])
    assert (args.plant, args.plant_model, args.effects) == (
        'mujoco',
        'm.yaml',
        ['torque_constant=0.7'],
    )


def test_sim_krang_declares_the_extended_model_parameter():
    from krang_sim.node import SimNodeParams

    assert SimNodeParams().plant_model == ''
    assert SimNodeParams(plant='mujoco', plant_model='m.yaml').plant_model == 'm.yaml'


def test_drive_chain_overrides_from_an_extended_model(robot, tmp_path):
    terms = plant_terms(robot, ['wheel_viscous_friction=3'], str(_extended_model(tmp_path / 'm')))
    o = drive_chain_overrides(terms.drive, drivetrain(robot))
    assert o == pytest.approx(
        {
            'adrc.torque_fraction': 0.58,
            'adrc.coulomb_compensation_nm': 8.0,
            'adrc.viscous_compensation_nm_s': 3.0,
            'balance_point.time_constant_s': 4.0,
        }
    )
    assert drive_chain_overrides(drivetrain(robot), drivetrain(robot)) == {
        'adrc.torque_fraction': 1.0,
        'adrc.coulomb_compensation_nm': 0.0,
        'adrc.viscous_compensation_nm_s': 0.0,
    }
    load_controller_config().override(o)  # valid parameters


def test_torque_fraction_and_friction_compensation_set_the_currents(robot):
    """A chain delivering 0.6 of the torque gets 1/0.6 of the current for the same wheel torque
    (the ground PD's too); the dry friction is added back as current of the weaker chain."""
    base = load_controller_config()
    beta = robot.nominal_beta
    nominal = BalanceController(robot, beta, base)
    weak = BalanceController(robot, beta, base.override({'adrc.torque_fraction': 0.6}))
    assert weak.k_motor == pytest.approx(0.6 * nominal.k_motor)
    assert weak.drive.torque_constant == pytest.approx(0.6 * nominal.drive.torque_constant)
    assert weak._ground_scale == pytest.approx(1 / 0.6)
    comp = BalanceController(
        robot,
        beta,
        base.override({'adrc.torque_fraction': 0.8, 'adrc.coulomb_compensation_nm': 4.0}),
    )
    assert comp._coulomb[0] == pytest.approx(4.0 / (0.8 * nominal.k_motor))
    assert nominal._coulomb == (0.0, 0.01, 0.0)
    with pytest.raises(ValueError):
        base.override({'adrc.torque_fraction': 0.0})


def _stream(det, seconds, q_mean, amplitude, period, speed_amp, drift=0.0, rate_hz=50.0, seed=0):
    """Feed a limit cycle: pitch q_mean + amplitude sin, wheel speed speed_amp cos (+ drift)."""
    rng = np.random.default_rng(seed)
    w = 2 * math.pi / period
    joints = np.zeros(16)
    out = []
    for k in range(int(seconds * rate_hz)):
        t = k / rate_hz
        q = q_mean + amplitude * math.sin(w * t) + rng.normal(0, 2e-4)
        p = det.update(
            t,
            q,
            amplitude * w * math.cos(w * t),
            speed_amp * math.cos(w * t) + drift,
            0.0,
            joints,
            False,
            gravity_pitch=q,
        )
        if p is not None:
            out.append(p)
    return out


def test_a_robot_in_a_small_limit_cycle_gives_its_mean_pitch():
    """A sticking drive chain keeps the robot in a limit cycle of a few mrad: the strict window
    never fills; the stationary window gives the mean pitch, with its standard error."""
    cfg = DetectorConfig()
    seconds = cfg.stationary_window_s + 4.0
    points = _stream(BalancedPoseDetector(cfg), seconds, -1.5, 0.003, 2.5, 0.05)
    assert len(points) == 1
    p = points[0]
    assert abs(p.q_base + 1.5) < 5e-4
    assert 0 < p.q_base_se < 1e-3
    assert p.window_s == pytest.approx(cfg.stationary_window_s, abs=0.05)


def test_a_wider_limit_cycle_gives_its_mean_with_an_honest_standard_error():
    """30 mrad of amplitude (the gear-hard chain's cycles are 20-30 mrad from peak to peak):
    the window is not a whole number of cycles, so its mean is off, by no more than twice the
    standard error the point carries (the learner weighs it by that)."""
    cfg = DetectorConfig()
    for period in (2.5, 3.1, 3.85):
        (p,) = _stream(
            BalancedPoseDetector(cfg), cfg.stationary_window_s + 4, -1.5, 0.03, period, 0.05
        )
        assert abs(p.q_base + 1.5) <= 2.0 * p.q_base_se, (period, p.q_base + 1.5, p.q_base_se)


def test_a_drifting_or_wide_limit_cycle_gives_no_point():
    cfg = DetectorConfig()
    seconds = cfg.stationary_window_s + 4.0
    assert not _stream(BalancedPoseDetector(cfg), seconds, -1.5, 0.003, 2.5, 0.05, 0.02)
    assert not _stream(BalancedPoseDetector(cfg), seconds, -1.5, 0.003, 2.5, 0.3)
    assert not _stream(BalancedPoseDetector(cfg), seconds, -1.5, 0.1, 2.5, 0.05)
    off = DetectorConfig(stationary_window_s=0.0)
    assert not _stream(BalancedPoseDetector(off), seconds, -1.5, 0.003, 2.5, 0.05)


def test_a_settling_robot_still_gives_its_strict_point_first():
    det = BalancedPoseDetector(DetectorConfig())
    points = _stream(det, 3.0, -1.5, 0.0, 2.5, 0.0)
    assert len(points) == 1 and points[0].window_s < 2.1


@pytest.fixture(scope='module')
def pose_pool(robot):
    return PosePool(robot)


def test_a_path_through_the_floor_is_refused(robot, pose_pool):
    """Two safe poses whose straight joint line passes a gripper through the floor (found in the
    pool: a pair whose midpoint collides), and the selector's refusal of it."""
    pool = pose_pool.generate(60, seed=7)
    start = pool.joints[0]
    clear = [pose_pool.path_clear(start, g) for g in pool.joints[1:]]
    assert any(clear)
    blocked = [i + 1 for i, c in enumerate(clear) if not c]
    assert blocked, 'the pool has no blocked path from its first pose'
    goal = pool.joints[blocked[0]]
    assert pose_pool.checker.is_free(pool.q_base[0], start)  # both ends are safe
    assert pose_pool.checker.is_free(pool.q_base[blocked[0]], goal)
    # the selector, asked to choose among blocked goals and one clear one, takes the clear one
    ok = next(i + 1 for i, c in enumerate(clear) if c)
    candidates = np.vstack([pool.joints[blocked[:5]], pool.joints[ok]])
    sel = AdaptiveSelector(robot, candidates, path_check=pose_pool.path_clear)
    beta = robot.nominal_beta
    choice = sel.choose(beta, np.eye(beta.size) * 1e-4, start)
    assert choice.index == len(candidates) - 1
    assert sel.refused <= 5


def test_a_goal_that_the_current_beta_puts_on_the_floor_is_refused(robot, pose_pool):
    """A pool pose is safe at the balance pitch of the pool's beta, but the robot balances where
    its true CoM puts it. The 20th move of a MuJoCo session (truth 7506, nominal chain): with the
    true beta the goal balances 64 mrad further forward than with the nominal one, and its left
    gripper touches the floor there; every pose inside the path is clear. The robot ran away at
    the current limit when the gripper landed. The path check includes the goal."""
    from krang_sim.truths import TruthRecipe, generate_truth

    start = np.array(
        [1.045, 1.0699, -2.8625, 1.4985, 0.9672, -0.4726, -1.6327, 0.0893,
         2.0382, -1.8715, -1.0598, -0.0014, 1.2987, -0.5222, -0.3719, 2.9079]
    )  # fmt: skip
    goal = np.array(
        [2.4768, 1.2052, -1.3314, 0.1297, -0.5599, 0.7375, -1.7127, 1.4203,
         1.3402, -2.0427, -0.779, -1.0295, 1.8012, -0.2758, 0.487, 2.7062]
    )  # fmt: skip
    truth = generate_truth(robot, 7506, TruthRecipe()).beta
    q_goal = balance_pitch(robot, np.stack([goal]), truth)[0]
    q_nominal = balance_pitch(robot, np.stack([goal]), robot.nominal_beta)[0]
    assert q_goal - q_nominal == pytest.approx(0.064, abs=0.002)
    assert pose_pool.checker.is_free(q_nominal, goal)
    assert ('lGripper_0', 'floor') in pose_pool.checker.colliding_pairs(q_goal, goal)
    inside = start + np.linspace(0.0, 1.0, 17)[1:-1, None] * (goal - start)
    q_inside = balance_pitch(robot, inside, truth)
    assert all(pose_pool.checker.is_free(q, j) for q, j in zip(q_inside, inside))
    assert not pose_pool.path_clear(start, goal, truth)
    assert pose_pool.path_clear(start, goal, robot.nominal_beta)


@pytest.mark.parametrize('plant', ['reduced', 'mujoco'])
@pytest.mark.parametrize('chain', ['gearmotor', 'gear-hard'])
def test_a_gearmotor_robot_stands_and_balances(robot, plant, chain):
    """Stand up and balance 20 s on each plant with a gearmotor drive chain, the controller told
    the chain: no safe stop, BALANCE reached, within 30 mrad of the true balance pitch over the
    last 8 s and the wheels within 0.15 m."""
    if plant == 'mujoco':
        pytest.importorskip('mujoco')
    from krang_model.beta import load_beta
    from krang_model.config import config_path

    truth = load_beta(config_path('sim_true_beta.yaml'), robot)
    terms = terms_from_strings(robot, campaign.CHAINS[chain])
    cfg = load_controller_config().override(drive_chain_overrides(terms.drive, drivetrain(robot)))
    run = run_balance(robot, truth, truth, seconds=20.0, plant=plant, terms=terms,
                      controller_config=cfg)  # fmt: skip
    e = run.extra
    assert e['final_mode'] == 'balance' and e['reached_balance_mode']
    last = run.t > run.t[-1] - 8.0
    err = e['q_base_true'][last] - e['balance_pitch_true'][last]
    x = e['x_true_m'][last]
    print(f'{plant} {chain}: |err| max {1e3 * np.abs(err).max():.1f} mrad, x {np.ptp(x):.3f} m')
    assert np.abs(err).max() < 0.03
    assert np.ptp(x) < 0.15


@pytest.mark.timeout(120)
def test_campaign_short(tmp_path):
    """The campaign's short version (one truth, the reduced plant, the gearmotor chain, 2
    poses): every run completes, no safe stop, each move's wheel excursion under the limit, the
    error falls below 3 mm."""
    params = campaign.short()
    result = campaign.run(params)
    text = campaign.report(result, tmp_path)
    print(text)
    for key, v in result['summary'].items():
        assert v['complete'] == v['runs'], key
        assert v['safe_stops'] == 0, key
        assert v['max_travel_m'] < campaign.TRAVEL_LIMIT_M, key
        assert v['worst_final_m'] < 3e-3, key
    assert (tmp_path / 'campaign.png').exists() and (tmp_path / 'campaign.json').exists()


def test_a_run_that_did_not_stand_up_counts_against_the_goals():
    """A cell that never stood up counts with its error before learning (the campaign records
    that), so the worst of its group is that error and the goals are not met."""
    learned = {'curve_m': [13e-3, 2e-3, 0.9e-3], 'learned': 2, 'failures': [], 'travel_m': [0.5]}
    fell = {'curve_m': [14e-3], 'learned': 0, 'failures': [[-1, 'did not stand up']]}
    cells = {('reduced', 'nominal', 1): learned, ('reduced', 'nominal', 2): fell}
    v = campaign.summarise(cells, 2)['reduced/nominal']
    assert (v['complete'], v['worst_final_m'], v['goals_met']) == (1, 14e-3, False)
    assert v['median_final_m'] == pytest.approx(0.5 * (0.9e-3 + 14e-3))


@pytest.mark.slow
@pytest.mark.timeout(4 * 3600)
def test_campaign_full(tmp_path):
    """Issue goal (a benchmark): 10 truths x both plants x {nominal, gearmotor}, 12 poses: every
    run completes, median < 1.0 mm and worst < 1.5 mm after 12 poses."""
    pytest.importorskip('mujoco')
    result = campaign.run(campaign.Params())
    print(campaign.report(result, tmp_path))
    for key, v in result['summary'].items():
        assert v['complete'] == v['runs'], key
        assert v['safe_stops'] == 0, key
        assert v['max_travel_m'] < campaign.TRAVEL_LIMIT_M, key
        assert v['goals_met'], key
