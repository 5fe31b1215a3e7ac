"""The experiments package: each experiment's run(params) on small settings, then report(result,
out_dir) writes what `krang experiment <name>` promises (the full runs are in the README and
docs)."""

import json

import numpy as np
import pytest

from krang_experiments import adrc_vs_lqr, learning, table2
from krang_experiments.common import setup
from krang_sim.scenarios import TABLE2_POSE, shifted_beta


def test_table2_run_and_report_on_given_betas(tmp_path, krang_data):
    robot, true_beta, _ = setup()
    betas = np.vstack(
        [robot.nominal_beta] * 15 + [shifted_beta(robot, true_beta, TABLE2_POSE, 0.01)]
    )
    np.savetxt(tmp_path / 'betas.txt', betas)
    params = table2.Params(
        runs=1, seconds=20.0, poses=16, kit=str(krang_data), betas=str(tmp_path / 'betas.txt')
    )
    result = table2.run(params, progress=False)
    assert [name for name, _ in result['rows']] == ['beta_0', 'beta_16', 'TRUE beta']
    assert set(result['table']) == {'beta_0', 'beta_16', 'TRUE beta'}
    assert (
        result['table']['beta_16']['stood_up'] == 1 and result['table']['beta_0']['refused'] == 1
    )
    out = tmp_path / 'out'
    text = table2.report(result, out)
    for name in (
        'report.md',
        'power_traces.png',
        'standup.png',
        'learning_curve.png',
        'table2.json',
        'learned_betas.txt',
        'beta_16.txt',
        'TRUE_beta.txt',
    ):
        assert (out / name).stat().st_size > 0, name
    assert (out / 'report.md').read_text() == text + '\n'
    assert f'krang experiment table2 --out {out} --runs 1 --poses 16' in text
    assert json.loads((out / 'table2.json').read_text())['table']['beta_16']['stood_up'] == 1
    np.testing.assert_allclose(np.loadtxt(out / 'learned_betas.txt'), betas, rtol=1e-11)


def test_adrc_vs_lqr_run_and_report(tmp_path):
    result = adrc_vs_lqr.run(adrc_vs_lqr.Params())
    assert len(result['results']) == 5
    for name, variant in result['summary'].items():
        assert variant['stood_up'] and variant['final_mode'] == 'balance', name
        assert [ph['name'] for ph in variant['phases']] == ['stand-up', 'push', 'pose change']
    text = adrc_vs_lqr.report(result, tmp_path)
    assert (tmp_path / 'adrc_vs_lqr.png').stat().st_size > 0
    assert (tmp_path / 'report.md').read_text() == text + '\n'
    assert json.loads((tmp_path / 'summary.json').read_text()).keys() == result['summary'].keys()
    assert text.count('| plain LQR |') == 3


def test_learning_run_and_report_on_a_small_pool(tmp_path):
    params = learning.Params(
        n_pool=400, n_betas=20, n_runs=2, n_test=50, parts=('filter', 'curves')
    )
    result = learning.run(params, progress=lambda message: None)
    res = result['results']
    assert res['settings']['n_pool'] == 400 and res['paper_filter']['filtered_poses'] > 0
    assert set(res['curves']) == {'paper', 'physical'}
    for setting, curves in res['curves'].items():
        for method, curve in curves.items():
            first, last = curve['0'], curve[max(curve, key=int)]
            assert last['balance_mm_mean'] < first['balance_mm_mean'], (setting, method)
    learning.report(result, tmp_path)
    assert (tmp_path / 'learning_curves.png').stat().st_size > 0
    assert not (tmp_path / 'real_data.png').exists()  # the real part was not asked for
    assert json.loads((tmp_path / 'learning_results.json').read_text())['settings']['n_runs'] == 2


@pytest.mark.slow  # 10-40 s: ten-fold CV of six estimators and the authors' pool
def test_learning_real_data_part_reproduces_the_documented_cross_validation(tmp_path, krang_data):
    """docs/learning.md, "Real data": 10-fold CV mean |x_com| 0.589 cm for the paper's GD, 0.211 cm
    for our MAP, 0.231 cm for it without the plausible region."""
    result = learning.run(
        learning.Params(data_dir=krang_data, parts=('real',)), progress=lambda message: None
    )
    cv = result['results']['real_data']['cross_validation']
    assert cv['paper-gd']['mean_cm'] == pytest.approx(0.589, abs=5e-4)
    assert cv['map']['mean_cm'] == pytest.approx(0.211, abs=5e-4)
    assert cv['map-unbounded']['mean_cm'] == pytest.approx(0.231, abs=5e-4)
    learned = result['results']['real_data']['learned']
    assert learned['physically_consistent'] and max(learned['com_moved_cm'].values()) <= 8.0
    assert result['results']['authors_pool']['authors_pool_6003_filtered_poses'] > 0
    learning.report(result, tmp_path)
    assert (tmp_path / 'real_data.png').stat().st_size > 0
    assert not (tmp_path / 'learning_curves.png').exists()
