"""krang learn on the real hardware data: output formats, physical consistency,
cross-validation."""

import json
import subprocess
import sys

import numpy as np
import pytest

import krang_com_estimator as est
from krang_model.beta import load_beta
from krang_model.robot import load_krang


@pytest.fixture(scope='module')
def robot():
    return load_krang()


def _learn(krang_data, out, *extra):
    cmd = [
        sys.executable,
        '-m',
        'krang_cli.main',
        'learn',
        '--poses',
        str(krang_data / 'hardware_balanced_poses_train.csv'),
        '--beta0',
        str(krang_data / 'betas' / 'betaVectors1initialBetahardwareAll190Vectors.txt'),
        '--row',
        '0',
        '--out',
        str(out),
        '--json',
        *extra,
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_map_txt_output_is_the_authors_format_and_physical(krang_data, tmp_path, robot):
    out = tmp_path / 'learned.txt'
    doc = _learn(krang_data, out, '--method', 'map', '--folds', '5')
    lines = out.read_text().splitlines()
    assert len(lines) == 1
    numbers = np.array([float(v) for v in lines[0].split()])
    assert numbers.shape == (92,)
    beta = load_beta(out, robot, row=0)
    assert np.allclose(beta, numbers)
    rep = est.physical_consistency(robot, beta)
    assert rep['ok'], rep['violations']
    assert doc['physically_consistent'] and doc['violations'] == []
    assert beta[0::4].sum() == pytest.approx(robot.nominal_mass, abs=1e-6)
    assert np.all(beta[0::4] > 0)
    for w in robot.wheel_body_ids:
        assert abs(beta[4 * w + 2]) < 1e-9 and abs(beta[4 * w + 3]) < 1e-9
    # better than where it started, on held-out records too
    assert doc['cv_mean_abs_xcom_m'] < doc['start_mean_abs_xcom_m']
    assert set(doc['com_moved_m']) == set(robot.body_names)


def test_paper_gd_reproduces_the_authors_last_row(krang_data, tmp_path, robot):
    out = tmp_path / 'gd.txt'
    doc = _learn(krang_data, out, '--method', 'paper-gd', '--folds', '0')
    traj = np.loadtxt(krang_data / 'betas' / 'betaVectors1initialBetahardwareAll190Vectors.txt')
    beta = load_beta(out, robot)
    assert np.abs(beta - traj[189]).max() <= 2.05e-4  # the kit's "2e-4" (2.02e-4 measured)
    assert not doc['physically_consistent']  # the authors' learned beta is not physical
    assert doc['in_sample_mean_abs_xcom_m'] == pytest.approx(0.00457, abs=2e-5)


def test_map_beats_paper_gd_on_held_out_records(krang_data, tmp_path):
    gd = _learn(krang_data, tmp_path / 'gd.yaml', '--method', 'paper-gd', '--folds', '5')
    mp = _learn(krang_data, tmp_path / 'map.yaml', '--method', 'map', '--folds', '5')
    assert mp['cv_mean_abs_xcom_m'] < gd['cv_mean_abs_xcom_m']
    assert mp['cv_mean_abs_pitch_deg'] < gd['cv_mean_abs_pitch_deg']


def test_yaml_output_and_mass_constrained_gd(krang_data, tmp_path, robot):
    out = tmp_path / 'gdm.yaml'
    doc = _learn(krang_data, out, '--method', 'paper-gd-mass', '--folds', '0')
    beta = load_beta(out, robot)
    assert beta[0::4].sum() == pytest.approx(robot.nominal_mass, abs=1e-9)
    assert doc['total_mass_kg'] == pytest.approx(robot.nominal_mass, abs=1e-9)
    text = out.read_text()
    assert 'method: paper-gd-mass' in text and 'lGripper' in text


def test_map_online_in_file_order(krang_data, tmp_path, robot):
    doc = _learn(krang_data, tmp_path / 'online.txt', '--method', 'map-online', '--folds', '0')
    beta = load_beta(tmp_path / 'online.txt', robot)
    assert beta[0::4].sum() == pytest.approx(robot.nominal_mass, abs=1e-6)
    assert doc['in_sample_mean_abs_xcom_m'] < 0.5 * doc['start_mean_abs_xcom_m']


def test_bad_input_is_a_clear_error(krang_data, tmp_path):
    res = subprocess.run(
        [
            sys.executable,
            '-m',
            'krang_cli.main',
            'learn',
            '--poses',
            str(tmp_path / 'none.csv'),
            '--beta0',
            str(krang_data / 'betas' / 'convergedBetaVector104PosesHardwareTrained.txt'),
            '--out',
            str(tmp_path / 'x.txt'),
        ],
        capture_output=True,
        text=True,
    )
    assert res.returncode != 0 and 'no such pose file' in res.stderr


BAD_BETA_FILES = {
    'settings.yaml': 'controller:\n  rate_hz: 500\n',  # valid YAML, not a beta file
    'list.yaml': '- 1\n- 2\n',
    'bodies.yaml': 'bodies: 3\n',
    'names.yaml': 'bodies:\n  - name: [1]\n',
    'broken.yaml': 'bodies: [1\n',
    'broken.json': '{"bodies": ',
    'binary.yaml': '\udcff\udcfe',
}


def _evaluate(beta):
    from krang_model.config import config_path

    return ['evaluate', '--beta', str(beta), '--poses', str(config_path('excitatory_poses.csv'))]


def test_evaluate_refuses_a_file_that_is_not_a_beta_in_one_line(tmp_path):
    """A YAML that is not a beta file: one line on stderr naming the file and the problem, a
    non-zero exit and nothing on stdout."""
    bad = tmp_path / 'settings.yaml'
    bad.write_text(BAD_BETA_FILES['settings.yaml'])
    res = subprocess.run(
        [sys.executable, '-m', 'krang_cli.main', *_evaluate(bad)], capture_output=True, text=True
    )
    assert res.returncode == 1 and res.stdout == ''
    assert res.stderr.splitlines() == [
        f'krang evaluate: error: {bad}: not a beta file: expected a mapping with a "bodies" list'
    ]


@pytest.mark.parametrize('name', sorted(BAD_BETA_FILES))
def test_evaluate_names_the_file_and_the_problem_of_any_bad_beta(tmp_path, capsys, name):
    from krang_cli.main import main

    bad = tmp_path / name
    bad.write_bytes(BAD_BETA_FILES[name].encode('utf-8', 'surrogateescape'))
    assert main(_evaluate(bad)) == 1
    out, err = capsys.readouterr()
    assert out == '' and len(err.splitlines()) == 1 and f'{bad}: ' in err
    assert 'Traceback' not in err
    assert main(_evaluate(tmp_path)) == 1  # a folder
    assert f'{tmp_path}: cannot read the beta file' in capsys.readouterr().err


def test_calibrated_map_with_a_pitch_offset_reports_its_scales(tmp_path, krang_data):
    s = _learn(
        krang_data,
        tmp_path / 'cal.yaml',
        '--method',
        'map',
        '--calibrate',
        '--pitch-offset-std',
        '0.035',
        '--folds',
        '0',
    )
    c = s['calibration']
    assert set(c) >= {'sigma_pitch_rad', 'mass_frac', 'com_std_m', 'log_evidence'}
    assert 0 < s['pitch_offset_std_rad'] < 0.035  # the data narrowed the 2-degree prior
    assert set(s['com_moved_std_m']) == set(s['com_moved_m'])
    assert c['mass_frac'] <= est.MASS_SPREAD / 2 + 1e-9  # within the plausible mass spread
    assert max(s['com_moved_m'].values()) <= est.COM_RADIUS_M + 1e-6
    assert s['physically_consistent'] and s['violations'] == []  # masses in range included
