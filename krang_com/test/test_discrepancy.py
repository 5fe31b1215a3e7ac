"""krang discrepancy: replay, locate, name, extend.

Each naming test hides ONE effect of the library (krang_model.effects) in the simulated plant and
runs the workflow on the record with the whole effect library; the workflow is not told which
effect, nor its value. The data generator (synthetic.simulate_record) is the reduced plant under
the ADRC BalanceController with the NOMINAL model, on the closed loop: sit, stand up, balance
through three pose changes with a +-3 A current excitation.

The replay is configured once for all simulated records with the simulator's own data-acquisition
property, never the hidden effect: the plant re-reduces a moving pose every 20 ms, so its body lags
the joints by 10 ms on average (pose_delay_s=0.01; without it the no-effect case sees a ~10 %
'viscous friction' in the moving-joint phases, the pose lag's signature). stride_s=0.1 keeps the
default run fast.

Stated tolerances: the named value within 5 % of the truth; the gap (whitened 4-signal RMS) shrinks
at least 2.5x and the held-out loss at least 4x (improvement >= 0.75); for the no-effect record,
nothing is named.
"""

import json
import math

import numpy as np
import pytest

from krang_model import effects as fx
from krang_discrepancy.loaders import load_bag_record, load_csv_record, save_bag
from krang_discrepancy.locate import locate
from krang_discrepancy.extended_model import load_extended_model, write_extended_model
from krang_discrepancy.fitting import Fit
from krang_discrepancy.naming import NamingConfig, gaps, name_effects
from krang_discrepancy.nominal import NominalModel
from krang_discrepancy.phases import PHASES, label_phases
from krang_discrepancy.record import Record
from krang_discrepancy.replay import Replay, ReplayConfig
from krang_discrepancy.report import run_discrepancy
from krang_discrepancy.synthetic import simulate_record
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_model.wip import WipDynamics, reduce_pose
from krang_sim.scenarios import TABLE2_POSE
from krang_sim.sensors import SensorNoise

SIM_REPLAY = dict(pose_delay_s=0.01, stride_s=0.1)
RECORD = dict(seconds=22.0, hold_s=2.0, sit_down=False)
NO_NOISE = SensorNoise(
    imu_pitch_std_rad=0.0,
    gyro_std_rad_s=0.0,
    gyro_lsb_rad_s=1e-12,
    accel_lsb_m_s2=1e-12,
    accel_std_m_s2=0.0,
    encoder_counts_per_rad=1e12,
    joint_std_rad=0.0,
)

# name, hidden effects {key: parameter}, true value in the reported unit, detail the report gives
CASES = [
    ('imu_pitch_bias', {'imu_pitch_bias': 0.02}, 0.02, {}),
    ('floor_slope', {'floor_slope': 0.02}, 0.02, {}),
    (
        'wheel_radius',
        {'wheel_radius': 0.25},
        0.25,
        {},
    ),  # the real question: 0.25 vs 0.2667 m
    ('payload', {'payload@lGripper': 5.0}, 5.0, {'link': 'lGripper'}),
    ('wheel_viscous_friction', {'wheel_viscous_friction': 2.0}, 2.0, {}),
    ('wheel_coulomb_friction', {'wheel_coulomb_friction': 2.0}, 2.0, {}),
    (
        'torque_constant',
        {'torque_constant': 0.8},
        0.8 * drivetrain(load_krang()).torque_constant,
        {},
    ),
    ('actuation_delay', {'actuation_delay': 0.02}, 0.02, {}),
    ('encoder_offset', {'encoder_offset@JWaist': 0.05}, 0.05, {'joint': 'JWaist'}),
    ('rolling_resistance', {'rolling_resistance': 4.0}, 4.0, {}),
]
VALUE_REL_TOL = 0.05
MIN_GAP_SHRINK = 2.5
MIN_HELDOUT_IMPROVEMENT = 0.75


@pytest.fixture(scope='module')
def model():
    return NominalModel.default()


def _name(record, model, **naming):
    rp = Replay([record], model, ReplayConfig(**SIM_REPLAY))
    res = name_effects(rp, config=NamingConfig(**naming))
    return rp, res


# ----------------------------------------------------------------------------- one test per effect


@pytest.mark.parametrize('name, hidden, truth, detail', CASES, ids=[c[0] for c in CASES])
def test_hidden_effect_is_named_with_value_and_the_gap_shrinks(name, hidden, truth, detail, model):
    rec = simulate_record(hidden, seed=3, **RECORD)
    assert 'effect' not in str(rec.meta).lower()  # the record does not carry the answer
    rp, res = _name(rec, model)
    assert res.name == name, [
        (f.key, round(f.improvement, 3), round(f.t, 1)) for f in res.singles[:4]
    ]
    sel = res.selected
    eff = sel.effects[0]
    value, unit = eff.display(float(sel.values[0]))
    assert value == pytest.approx(truth, rel=VALUE_REL_TOL), (value, truth, unit)
    assert sel.uncertainty[0] > 0 and math.isfinite(sel.uncertainty[0])
    for k, v in detail.items():
        assert eff.detail[k] == v
    g = gaps(rp, model.terms(), res)
    assert g['before']['gap'] / g['after']['gap'] >= MIN_GAP_SHRINK, g
    assert sel.improvement >= MIN_HELDOUT_IMPROVEMENT
    assert len(sel.effects) == 1  # no spurious second effect


def test_no_hidden_effect_names_none(model):
    rec = simulate_record(None, seed=3, **RECORD)
    rp, res = _name(rec, model)
    assert res.name == 'none', [
        (f.key, round(f.improvement, 3), round(f.t, 1)) for f in res.singles[:3]
    ]
    assert res.selected is None
    best = res.singles[0]
    assert best.improvement < NamingConfig().min_improvement or best.t < NamingConfig().min_t


# ----------------------------------------------------------------------------- the replay itself


def _wip_record(model, seconds=3.0, seed=0):
    """A record made by krang_model.wip.WipDynamics itself (1 ms semi-implicit Euler) under random
    piecewise-constant torques around upright, no controller, no noise."""
    rng = np.random.default_rng(seed)
    body = reduce_pose(model.robot, TABLE2_POSE, model.beta)
    dyn = WipDynamics(body, model.drive)
    dt, n = 1e-3, int(seconds / 1e-3)
    state = [0.0, -body.com_offset + 0.01, 0.0, 0.0, 0.0, 0.0]
    t, q, dq, w, dw, cmd_t, cmd = [], [], [], [], [], [], []
    u = (0.0, 0.0)
    for k in range(n):
        if k % 4 == 0:
            # a stabilising PD on pitch plus noise so the pendulum stays near upright
            theta = state[1] + body.com_offset
            tau = 300.0 * theta + 60.0 * state[3] + 2.0 * state[2] + rng.normal(0, 5.0)
            u = (tau / 2, tau / 2)
            cmd_t.append(k * dt)
            cmd.append(u)
        t.append(k * dt)
        q.append(state[1])
        dq.append(state[3])
        w.append(state[0] - state[1])
        dw.append(state[2] - state[3])
        state = dyn.step(state, u[0], u[1], dt)
    return Record(
        t=t,
        q_base=q,
        pitch_rate=dq,
        wheel=w,
        wheel_rate=dw,
        joints=np.tile(TABLE2_POSE, (n, 1)),
        cmd_t=cmd_t,
        cmd_torque=cmd,
        name='wip',
    )


def test_replay_reproduces_wipdynamics_exactly(model):
    rec = _wip_record(model)
    rp = Replay(
        [rec],
        model,
        ReplayConfig(horizon_s=0.2, stride_s=0.1, substep_s=1e-3, smooth_s=0.0),
        phases=PHASES,
    )
    res = rp.residuals([model.terms()])[0]
    assert len(rp) > 10
    assert np.abs(res).max() < 1e-9


def test_every_library_effect_reproduces_the_simulator(model):
    """All nine effects at once in the plant, no sensor noise: the replay with the true values
    predicts the simulator to ~1e-4 rad (integration and pose-update differences only) while the
    nominal model is off by centimetres of wheel travel."""
    hidden = {
        'imu_pitch_bias': 0.01,
        'floor_slope': 0.01,
        'wheel_radius': 0.26,
        'payload@lGripper': 3.0,
        'wheel_viscous_friction': 0.5,
        'wheel_coulomb_friction': 0.5,
        'torque_constant': 0.9,
        'actuation_delay': 0.004,
        'encoder_offset@JWaist': 0.02,
    }
    rec = simulate_record(hidden, seconds=14.0, seed=1, noise=NO_NOISE, hold_s=1.5, sit_down=False)
    rp = Replay([rec], model, ReplayConfig(**SIM_REPLAY))
    truth = fx.model_terms(hidden, model.terms())  # the plant's terms are the replay's
    r0, r1 = rp.residuals([model.terms(), truth])
    w = rp.win_phase == 'balancing'
    assert np.sqrt(np.mean(r1[w][:, -1, 0] ** 2)) < 2e-4
    assert np.sqrt(np.mean(r0[w][:, -1, 0] ** 2)) > 20 * np.sqrt(np.mean(r1[w][:, -1, 0] ** 2))


# ----------------------------------------------------------------------------- phases and locate


def test_phases_follow_the_controller_modes(model):
    rec = simulate_record(None, seconds=24.0, seed=2, hold_s=2.0, sit_down=True)
    lab = label_phases(rec)
    mode = rec.meta['mode']
    assert (
        np.mean(lab[mode <= 0] == 'sitting') > 0.7
    )  # safe stop / sit before standing and after sitting
    assert 'standing_up' in set(lab) and 'moving_joints' in set(lab) and 'sitting_down' in set(lab)
    assert np.mean(lab[mode == 2] != 'sitting') > 0.95
    rp = Replay([rec], model, ReplayConfig(**SIM_REPLAY))
    loc = locate(rp)
    assert set(loc.phase_stats) >= {'sitting', 'standing_up', 'balancing', 'moving_joints'}
    for ph in loc.phase_stats.values():
        assert ph['q_base']['rms'] < 5e-3  # no effect: noise-level errors


def test_locate_points_at_the_biased_signals(model):
    rec = simulate_record({'floor_slope': 0.02}, seed=4, **RECORD)
    rp = Replay([rec], model, ReplayConfig(**SIM_REPLAY))
    loc = locate(rp)
    st = loc.phase_stats['balancing']
    assert abs(st['wheel_rate']['bias_z']) > 5 and abs(st['q_base']['bias_z']) > 5
    assert loc.decorrelation_s['wheel_rate'] > rp.horizon  # structure, not noise
    assert any('systematic' in s for s in loc.summary)


# ----------------------------------------------------------------------------- library, YAML, loa


def test_user_effect_registers_and_changes_the_model(model):
    @fx.register_effect
    class PitchSpring(fx.Effect):
        name = 'test_pitch_spring'
        unit = 'N m/rad'
        bounds = (-200.0, 200.0)
        scale = 10.0

        def apply(self, terms, value):
            terms.extra_forces.append(lambda s, k=value: (0.0 * s.q_base, -k * (s.q_base + 1.55)))

    try:
        assert 'test_pitch_spring' in fx.EFFECTS
        eff = fx.get_effect('test_pitch_spring')
        rec = _wip_record(model, seconds=1.5)
        rp = Replay([rec], model, ReplayConfig(horizon_s=0.2, stride_s=0.1), phases=PHASES)
        a, b, c = rp.predict(
            [
                model.terms(),
                fx.apply_effects(model.terms(), [eff], [0.0]),
                fx.apply_effects(model.terms(), [eff], [50.0]),
            ]
        )
        assert np.array_equal(a, b) and np.abs(a - c).max() > 1e-4
    finally:
        fx.unregister_effect('test_pitch_spring')


def test_extended_model_yaml_round_trip(tmp_path, model):
    effs = [
        fx.get_effect('floor_slope'),
        fx.get_effect('payload@rGripper'),
        fx.get_effect('torque_constant'),
    ]
    fit = Fit(
        effs,
        np.array([0.01, 2.0, 0.9]),
        np.array([1e-4, 0.1, 0.01]),
        0.0,
        np.zeros(1),
        np.zeros((2, 3)),
    )
    path = tmp_path / 'ext.yaml'
    write_extended_model(path, fit, model)
    terms = load_extended_model(path)
    assert terms.payloads == (('rGripper', (0.0, 0.0, 0.1), 2.0),)
    assert terms.drive.floor_slope == 0.01
    assert terms.drive.torque_constant == pytest.approx(
        0.9 * model.drive.torque_constant, rel=1e-15
    )


def test_an_extended_model_file_users_keep_still_loads(model):
    """test/data/extended_model_v1.yaml, a file of format 1 that holds a ``sim_effects`` section
    beside the effects list, loads: the effects list gives the robot."""
    from pathlib import Path

    path = Path(__file__).resolve().parent / 'data' / 'extended_model_v1.yaml'
    terms = load_extended_model(path, model.terms())
    d = model.drive
    assert terms.drive.floor_slope == 0.0123
    assert terms.drive.torque_constant == pytest.approx(0.91 * d.torque_constant, rel=1e-15)
    assert terms.drive.ground_viscous == d.ground_viscous + 1.75
    assert terms.payloads == (('lGripper', (0.0, 0.0, 0.1), 2.5),)
    assert terms.actuation_delay == 0.0 and terms.imu_pitch_bias == 0.0


def test_bag_round_trip(tmp_path):
    rec = simulate_record(None, seconds=6.0, seed=5, programme=(), sit_down=False)
    path = save_bag(rec, tmp_path / 'run.mcap', rate_hz=200.0)
    back = load_bag_record(path)
    assert back.period == pytest.approx(0.005, rel=1e-3)
    assert back.cmd_t.size == rec.cmd_t.size
    np.testing.assert_allclose(back.cmd_torque, rec.cmd_torque)
    t = back.t + rec.t[0]
    # the IMU times are read as integer ns here; krang_bag.reader gives the joint states as float
    # seconds since 1970 (0.24 us resolution), which costs the fast-moving wheel signals ~1e-5
    for k, tol in (('q_base', 1e-9), ('pitch_rate', 1e-9), ('wheel', 1e-4), ('wheel_rate', 1e-4)):
        np.testing.assert_allclose(
            getattr(back, k), np.interp(t, rec.t, getattr(rec, k)), atol=tol
        )
    np.testing.assert_allclose(back.cmd_t, rec.cmd_t - rec.t[0], atol=1e-6)


def test_hardware_csv_loader(krang_data):
    path = krang_data / 'balancing_runs' / 'table2' / 'beta190_trial0.csv'
    rec = load_csv_record(path)
    raw = np.loadtxt(path, delimiter=',', skiprows=1)
    assert rec.duration == pytest.approx(raw[:, 0].sum() - raw[0, 0], abs=0.05)
    assert rec.period == pytest.approx(0.0333, abs=0.001)
    assert rec.cmd_t.size == raw.shape[0]
    # wheel + q_base is the logged x_wheel (ground-referenced)
    t_raw = np.cumsum(raw[:, 0]) - raw[0, 0]
    np.testing.assert_allclose(
        np.interp(rec.t[10:-10], t_raw, raw[:, 5]),
        rec.wheel[10:-10] + rec.q_base[10:-10],
        atol=1e-9,
    )
    lab = label_phases(rec)
    assert lab[0] == 'sitting' and 'standing_up' in set(lab) and 'balancing' in set(lab)


# ----------------------------------------------------------------------------- the command


def test_cli_end_to_end_on_a_bag(tmp_path, capsys):
    from krang_cli.main import main

    rec = simulate_record({'floor_slope': 0.015}, seed=6, **RECORD)
    bag = save_bag(rec, tmp_path / 'session.mcap', rate_hz=200.0)
    out = tmp_path / 'disc'
    code = main(
        [
            'discrepancy',
            '--measured',
            str(bag),
            '--out',
            str(out),
            '--json',
            '--pose-delay',
            '0.01',
            '--stride',
            '0.1',
        ]
    )
    assert code == 0
    js = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ('effect', 'value', 'unit', 'uncertainty', 'gap_before', 'gap_after'):
        assert key in js
    assert js['effect'] == 'floor_slope' and js['unit'] == 'rad'
    assert js['value'] == pytest.approx(0.015, rel=VALUE_REL_TOL)
    assert js['gap_after'] < js['gap_before'] / MIN_GAP_SHRINK
    for f in (
        'report.md',
        'extended_model.yaml',
        'locate_timeseries.png',
        'naming_evidence.png',
        'gap_timeseries.png',
        'gap_phases.png',
    ):
        assert (out / f).exists(), f
    terms = load_extended_model(out / 'extended_model.yaml')
    assert terms.drive.floor_slope == pytest.approx(js['value'])
    assert 'floor_slope' in (out / 'report.md').read_text()


def test_cli_help_explains():
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, '-m', 'krang_cli.main', 'discrepancy', '--help'],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for word in (
        '--measured',
        '--out',
        '--json',
        'held-out',
        'imu_pitch_bias',
        'extended_model.yaml',
        '--max-windows N at most N windows',
        f'(default {ReplayConfig.max_total_windows}:',  # the help names the replay's budget
    ):
        assert word in ' '.join(out.split())


def test_records_beyond_the_window_budget_widen_the_stride_alike():
    """Over ``max_total_windows`` the stride widens, for every record alike, to the narrowest
    whole number of samples that keeps the total within the budget; below it nothing changes."""
    recs = [simulate_record({}, seconds=s, seed=k, hold_s=1.5) for k, s in ((3, 12.0), (4, 20.0))]
    model = NominalModel.default()
    free = Replay(recs, model, ReplayConfig(stride_s=0.02, max_total_windows=0))
    assert free.stride_s == 0.02 and free.unwidened_windows == len(free)
    budget = len(free) // 3 + 7
    tight = Replay(recs, model, ReplayConfig(stride_s=0.02, max_total_windows=budget))
    assert tight.unwidened_windows == len(free) and len(tight) <= budget
    period = recs[0].period
    samples = round(tight.stride_s / period)
    assert tight.stride_s == pytest.approx(samples * period)
    for ri in range(2):  # every record's windows at that stride
        starts = tight.win_t[tight.win_record == ri]
        assert np.allclose(np.diff(starts), samples * period)
    # one sample narrower would hold more windows than the budget
    narrower = Replay(
        recs, model, ReplayConfig(stride_s=(samples - 1) * period, max_total_windows=0)
    )
    assert len(narrower) > budget
    same = Replay(recs, model, ReplayConfig(stride_s=0.02, max_total_windows=len(free)))
    assert np.array_equal(same.win_t, free.win_t)


# ----------------------------------------------------------------------------- combinations; slow


def test_two_hidden_effects_are_named_as_a_pair(model):
    """Slope and delay hidden together: the slope is accepted first, its near-duplicates (IMU bias,
    payload, encoder offset) add nothing, and the delay enters as the second effect."""
    rec = simulate_record(
        {'floor_slope': 0.015, 'actuation_delay': 0.02},
        seconds=30.0,
        seed=8,
        hold_s=2.5,
        sit_down=False,
    )
    rp, res = _name(rec, model)
    assert sorted(e.name for e in res.selected.effects) == ['actuation_delay', 'floor_slope']
    vals = {
        e.name: e.display(float(v))[0] for e, v in zip(res.selected.effects, res.selected.values)
    }
    assert vals['floor_slope'] == pytest.approx(0.015, rel=VALUE_REL_TOL)
    assert vals['actuation_delay'] == pytest.approx(0.02, rel=VALUE_REL_TOL)


@pytest.mark.slow
@pytest.mark.parametrize('seed', [11, 12, 13])
def test_no_effect_stays_none_over_seeds_at_the_default_stride(seed, model):
    rec = simulate_record(None, seconds=30.0, seed=seed, hold_s=2.5, sit_down=True)
    rp = Replay([rec], model, ReplayConfig(pose_delay_s=0.01))
    assert name_effects(rp).name == 'none'


@pytest.mark.slow
def test_real_hardware_run_report(krang_data, tmp_path):
    """The workflow runs end to end on one Table II run; what it finds is documented in
    docs/discrepancy.md, not asserted here (there is no ground truth)."""
    out = run_discrepancy(
        [krang_data / 'balancing_runs' / 'table2' / 'beta190_trial0.csv'], tmp_path, plots=False
    )
    js = out['json']
    assert ('effect' in js) or ('effects' in js)
    assert math.isfinite(js['gap_before'])
    assert (tmp_path / 'report.md').exists() and (tmp_path / 'extended_model.yaml').exists()
