"""krang discrepancy: 'unexplained' as an answer, judging new data against a baseline, and the
selection rule.

The hidden effects are put in the simulated plant (krang_discrepancy.synthetic.simulate_record);
effects outside the library are made around it (``Unmodelled``). The workflow is told neither.
"""

import math

import numpy as np
import pytest
import yaml

from krang_model import effects as fx
from krang_discrepancy.evidence import compare
from krang_discrepancy.fitting import scan_grid, start_value
from krang_discrepancy.replay import ReplayConfig
from krang_discrepancy.extended_model import load_extended_model
from krang_discrepancy.report import run_discrepancy
from krang_discrepancy.synthetic import VALIDATION_SUITE, Unmodelled, simulate_record
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

SIM_REPLAY = ReplayConfig(pose_delay_s=0.01, stride_s=0.1)
RECORD = dict(seconds=22.0, hold_s=2.0, sit_down=False)
KT = drivetrain(load_krang()).torque_constant


def _run(rec, out, **kw):
    return run_discrepancy([rec], out, plots=False, replay_config=SIM_REPLAY, **kw)


def _named(js):
    items = js.get('effects') or ([js] if js['effect'] not in ('none', 'unexplained') else [])
    return {e['effect']: e for e in items}


# ----------------------------------------------------------------------------- selection rule


def test_scan_grid_holds_every_effects_zero():
    """The coarse scan can always choose 'no change' (the wheel radius's nominal 0.2667 m fell
    between the 0.02 m grid points, so it lost every conditional scan)."""
    base = fx.ModelTerms.nominal(fx.nominal_drive())
    for e in fx.library():
        assert np.any(np.isclose(scan_grid(e, base), start_value(e, base), rtol=0, atol=1e-12))
    radius = fx.get_effect('wheel_radius')
    assert not np.any(np.isclose(np.linspace(*radius.bounds, 9), start_value(radius, base)))


def test_weighted_t_admits_concentrated_evidence_and_rarely_noise():
    """Evidence in 3 of 30 blocks (where the effect changes the predictions) passes the weighted
    test, not the equal-weight one; on noise (the effect's visibility unrelated to the log ratios)
    the weighted test with >= 4 effective blocks passes t >= 3 in < 2 % of draws."""
    rng = np.random.default_rng(0)
    n_blocks, per = 30, 10
    blocks = np.repeat(np.arange(n_blocks), per)
    mask = np.ones(blocks.size, bool)
    ref = np.ones(blocks.size)
    new = ref * np.exp(-rng.normal(0, 0.05, blocks.size))
    new[blocks < 3] *= 0.3  # the effect shows in 3 blocks only
    weight = np.where(blocks < 3, 1.0, 0.02)
    imp, t, _, tw, n_eff = compare(ref, new, blocks, mask, weight)
    assert t < 3 <= tw
    assert n_eff < 4 or tw >= 3
    false = 0
    draws = 2000
    for _ in range(draws):
        d = rng.normal(0, 0.1, n_blocks)
        w = rng.gamma(0.5, 1.0, n_blocks)
        new = ref * np.exp(-np.repeat(d, per))
        _, _, _, tw, n_eff = compare(ref, new, blocks, mask, np.repeat(w, per) / per)
        false += tw >= 3 and n_eff >= 4
    assert false / draws < 0.02


# ----------------------------------------------------------------------------- unexplained


def test_out_of_library_deadband_is_unexplained_with_a_signature(tmp_path):
    """A 2 A drive deadband was read as a torque constant (0.57 x); now: unexplained, with the
    partial library correction, the signature, and no name in the JSON's `effect`."""
    rec = simulate_record(None, seed=3, unmodelled=Unmodelled(drive_deadband_a=2.0), **RECORD)
    out = _run(rec, tmp_path)
    js = out['json']
    assert js['effect'] == 'unexplained', js
    assert js['value'] is None and js['reason']
    sig = js['signature']
    assert sig['significant'] and sig['improvement'] >= 0.10 and sig['t'] >= 3
    assert set(sig['signals']) == {'q_base', 'pitch_rate', 'wheel', 'wheel_rate'}
    assert sig['phases'] and sig['features'] and sig['decorrelation_s']
    doc = yaml.safe_load((tmp_path / 'extended_model.yaml').read_text())
    assert doc['verdict'] == 'unexplained'
    assert 'unexplained' in (tmp_path / 'report.md').read_text()


def test_no_effect_is_none_and_its_residual_unstructured(tmp_path):
    rec = simulate_record(None, seed=12, **RECORD)
    js = _run(rec, tmp_path)['json']
    assert js['effect'] == 'none', js
    assert not js['signature']['significant']
    assert not js['gap_test']['exceeds'] and js['gap_test']['gap'] < 1.0


def test_an_arm_encoder_offset_is_unexplained_where_the_arm_swings(tmp_path):
    """A 0.1 rad offset of the left shoulder's encoder (LJ2), outside the library: no effect
    is admitted (the offset moves the CoM only in the poses that swing the arm), so the rule
    alone would answer 'none'. The gap on the balancing windows exceeds what a right model shows
    (verdict.MAX_OWN_GAP): 'unexplained', with the stretches that carry the excess, each in a
    pose that has LJ2 away from the first pose."""
    hidden = {fx.EncoderOffset('LJ2'): 0.1}
    js = _run(simulate_record(hidden, seed=3, **RECORD), tmp_path)['json']
    assert js['effect'] == 'unexplained', js
    gt = js['gap_test']
    assert gt['exceeds'] and gt['gap'] > gt['limit']
    assert 'quiet balancing windows' in js['reason']
    assert gt['stretches'] and 'LJ2' in gt['joints_in_every_stretch']
    assert sum(s['share'] for s in gt['stretches']) > 0.5


def test_the_gap_test_applies_on_the_models_own_yardstick_only():
    """Nothing named, the residual test quiet: a gap on the balancing windows above the limit
    gives 'unexplained' on the model's own yardstick; judged against a baseline MAX_GAP rules."""
    from types import SimpleNamespace
    from krang_discrepancy.verdict import decide
    from krang_discrepancy.verdict import MAX_OWN_GAP, Structure

    quiet = Structure(0.0, 0.0, False)
    nothing = SimpleNamespace(selected=None)
    gaps = {'after': {'gap': 1.0}}
    over = {
        'gap': 1.5 * MAX_OWN_GAP,
        'limit': MAX_OWN_GAP,
        'exceeds': True,
        'signals': {},
        'phases': {},
        'stretches': [],
        'joints_in_every_stretch': [],
    }
    assert decide(nothing, quiet, gaps, False, excess=over)[0] == 'unexplained'
    assert decide(nothing, quiet, gaps, True, excess=over)[0] == 'none'
    assert decide(nothing, quiet, gaps, False, excess=dict(over, exceeds=False))[0] == 'none'


# ----------------------------------------------------------------------------- baselines


def test_far_off_a_baseline_is_unexplained_not_none():
    """Judged in a baseline's units, a model still > MAX_GAP x its typical error off after the
    library effects is 'unexplained' even when nothing is named and the residual test is quiet;
    without a baseline the same figures give 'none'."""
    from types import SimpleNamespace
    from krang_discrepancy.verdict import decide
    from krang_discrepancy.verdict import MAX_GAP, Structure

    quiet = Structure(0.0, 0.0, False)
    nothing = SimpleNamespace(selected=None)
    far = {'after': {'gap': 4.0 * MAX_GAP}}
    assert decide(nothing, quiet, far, True)[0] == 'unexplained'
    assert decide(nothing, quiet, far, False)[0] == 'none'
    assert decide(nothing, quiet, {'after': {'gap': 0.5 * MAX_GAP}}, True)[0] == 'none'


def test_the_baseline_gap_is_matched_phase_for_phase():
    """A right model on a record that never leaves the caster, where the baseline's own errors
    were twice its balancing ones, is 1x off, not 2x; a model 3x off in every phase is 3x off,
    whatever the mix of phases. (Before: the raw gap in the baseline's scales, 2.0-2.2 for the
    right 5 kg payload below, which sits for the whole record, so 'unexplained' or not by the
    machine's rounding.)"""
    from types import SimpleNamespace
    from krang_discrepancy.verdict import phase_gaps, phase_matched_gap

    rng = np.random.default_rng(0)
    scales = np.full((3, 4), 0.01)

    def replay(phases):
        return SimpleNamespace(
            scales=scales, active=np.ones(len(phases), bool), win_phase=np.array(phases)
        )

    own_size = {'sitting': 2.0, 'balancing': 1.0}
    baseline = replay(['sitting'] * 50 + ['balancing'] * 150)
    noise = rng.standard_normal((200, 3, 4)) * scales
    own = noise * np.array([own_size[p] for p in baseline.win_phase])[:, None, None]
    stored = phase_gaps(baseline, own, scales)
    assert stored['sitting'] == pytest.approx(2.0, rel=0.05)
    assert stored['balancing'] == pytest.approx(1.0, rel=0.05)
    sits = replay(['sitting'] * 200)
    right = 2.0 * rng.standard_normal((200, 3, 4)) * scales
    raw = float(np.sqrt(np.mean((right / scales) ** 2)))
    assert raw == pytest.approx(2.0, rel=0.05)
    assert phase_matched_gap(sits, right, stored) == pytest.approx(1.0, rel=0.05)
    assert phase_matched_gap(baseline, 3.0 * own, stored) == pytest.approx(3.0, rel=0.05)
    assert phase_matched_gap(sits, right, {}) == pytest.approx(raw)  # an older baseline file


@pytest.mark.slow
def test_baseline_chain_of_two_names_what_changed_in_physical_units(tmp_path):
    """A: slope 0.02 rad (its own run). B = A + torque constant 0.8 x, judged against A: names
    the torque constant as N m/A, its file holds slope + Kt. C = B + 5 kg on the left gripper,
    judged against B: names the payload; its file holds all three and the terms a plant is
    built with from it carry all three. C's robot never stands up (its record is the caster and
    the attempts), so it is judged phase for phase against B's own errors."""
    slope = {'floor_slope': 0.02}
    kt = {'floor_slope': 0.02, 'torque_constant': 0.8}
    pay = {'floor_slope': 0.02, 'torque_constant': 0.8, 'payload@lGripper': 5.0}
    a = _run(simulate_record(slope, seed=3, **RECORD), tmp_path / 'a')['json']
    assert a['effect'] == 'floor_slope'
    ya = tmp_path / 'a' / 'extended_model.yaml'
    b = _run(simulate_record(kt, seed=4, **RECORD), tmp_path / 'b', baseline=ya)['json']
    assert set(_named(b)) == {'torque_constant'}, b
    assert b['unit'] == 'N m/A'
    assert b['value'] == pytest.approx(0.8 * KT, rel=0.05)
    assert b['gap_before'] > 2.0 * b['gap_after']  # in A's own units: B's model is far off
    yb = tmp_path / 'b' / 'extended_model.yaml'
    doc_b = yaml.safe_load(yb.read_text())
    assert [e['effect'] for e in doc_b['effects']] == ['floor_slope', 'torque_constant']
    c = _run(simulate_record(pay, seed=5, **RECORD), tmp_path / 'c', baseline=yb)['json']
    assert set(_named(c)) == {'payload'}, c
    assert c['value'] == pytest.approx(5.0, rel=0.05)
    assert c['gap_matched'][1] < 1.5  # the raw gap: 2.0-2.2 (seeds 5-9)
    terms = load_extended_model(tmp_path / 'c' / 'extended_model.yaml')
    assert terms.drive.floor_slope == pytest.approx(0.02, rel=0.05)
    assert terms.drive.torque_constant == pytest.approx(0.8 * KT, rel=0.05)
    [(link, _, kg)] = terms.payloads
    assert link == 'lGripper' and kg == pytest.approx(5.0, rel=0.05)


@pytest.mark.slow
def test_records_that_disagree_raise_the_misattribution_warning(tmp_path):
    """Two records of 'one robot' whose torque constants differ (0.8 x and 0.6 x): pooled, the
    per-record refits disagree far beyond their uncertainty and the report says so."""
    recs = [
        simulate_record({'torque_constant': k}, seed=s, name=f'run{s}', **RECORD)
        for k, s in ((0.8, 3), (0.6, 4))
    ]
    out = run_discrepancy(recs, tmp_path, plots=False, replay_config=SIM_REPLAY)
    js = out['json']
    per = js['per_record']['effects']['torque_constant']
    assert per['values'][0] == pytest.approx(0.8 * KT, rel=0.05)
    assert per['values'][1] == pytest.approx(0.6 * KT, rel=0.05)
    assert 'torque_constant' in js['misattribution_warning']
    assert 'misattributed' in (tmp_path / 'report.md').read_text()


# ----------------------------------------------------------------------------- the suite (slow)


#: The suite's known wrong answers (docs/discrepancy.md §6), kept visible: strict, so a fix shows.
KNOWN_MISSES = {}
SUITE = [
    pytest.param(c, marks=pytest.mark.xfail(strict=True, reason=KNOWN_MISSES[c[0]]))
    if c[0] in KNOWN_MISSES
    else c
    for c in VALIDATION_SUITE
]


@pytest.mark.slow
@pytest.mark.parametrize('case', SUITE, ids=[c[0] for c in VALIDATION_SUITE])
def test_validation_suite(case, tmp_path):
    """Every case of the suite: no effect -> none; library effects -> their names, values within
    10 % and 4 sigma; outside the library -> unexplained or the stated equivalent."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / 'bench' / 'bench_discrepancy.py'
    spec = importlib.util.spec_from_file_location('bench_discrepancy', path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    r = bench.hidden_case(case)
    assert r['right'], r
    for c in r['checks']:
        assert abs(c['rel_err']) <= 0.10 and (abs(c['z']) <= 4 or math.isinf(c['z'])), r
