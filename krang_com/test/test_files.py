"""Files a user keeps are written atomically, and bad input files give one clear line."""

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from krang_cli.main import main as krang
from krang_model.beta import BetaFileError, load_beta, save_beta
from krang_model.files import atomic_open, write_text
from krang_model.poses import PoseFileError, load_poses, save_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang


@pytest.fixture(scope='module')
def robot():
    return load_krang()


def test_reader_never_sees_a_partial_beta(robot, tmp_path):
    """A save loop and a read loop at once: every read parses to one of the written betas."""
    path = tmp_path / 'beta.yaml'
    betas = [robot.nominal_beta * (1 + 0.01 * k) for k in range(5)]
    save_beta(path, betas[0], robot)
    stop = threading.Event()
    reads = {'ok': 0, 'bad': []}

    def reader():
        while not stop.is_set():
            text = path.read_text()
            try:
                beta = load_beta(path, robot)
                assert any(np.allclose(beta, b, rtol=1e-8) for b in betas)
                reads['ok'] += 1
            except Exception as err:  # noqa: BLE001 - record any failure, assert below
                reads['bad'].append(f'{err!r}: {len(text)} chars')

    thread = threading.Thread(target=reader)
    thread.start()
    for k in range(300):
        save_beta(path, betas[k % len(betas)], robot)
    stop.set()
    thread.join()
    assert reads['ok'] > 50 and not reads['bad'], reads['bad'][:3]
    assert not [p for p in tmp_path.iterdir() if p.name != 'beta.yaml'], 'temporary files left'


def test_sigkill_while_saving_leaves_a_whole_file(tmp_path):
    """SIGKILL a process that saves in a loop: the file on disk is always a whole beta."""
    path = tmp_path / 'beta.yaml'
    code = (
        'import sys; from krang_model.beta import save_beta; from krang_model.robot import '
        'load_krang; r = load_krang(); b = r.nominal_beta\n'
        'save_beta(sys.argv[1], b, r); print("ready", flush=True)\n'
        'while True: save_beta(sys.argv[1], b, r)\n'
    )
    robot = load_krang()
    for delay in (0.05, 0.11, 0.23, 0.37, 0.5):
        proc = subprocess.Popen([sys.executable, '-c', code, str(path)], stdout=subprocess.PIPE)
        assert proc.stdout.readline().strip() == b'ready'
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        np.testing.assert_allclose(load_beta(path, robot), robot.nominal_beta)


def test_failed_write_keeps_the_old_file(tmp_path):
    path = write_text(tmp_path / 'report.md', 'old\n')
    with pytest.raises(RuntimeError):
        with atomic_open(path) as f:
            f.write('half of the new')
            raise RuntimeError('the job failed half-way')
    assert path.read_text() == 'old\n'
    assert [p.name for p in tmp_path.iterdir()] == ['report.md']


def test_missing_output_folder_is_an_error_not_a_new_tree(robot, tmp_path):
    target = tmp_path / 'no' / 'such' / 'beta.yaml'
    with pytest.raises(FileNotFoundError, match='does not exist'):
        save_beta(target, robot.nominal_beta, robot)
    assert not (tmp_path / 'no').exists()


def test_saved_files_have_normal_permissions(robot, tmp_path):
    path = save_beta(tmp_path / 'beta.txt', robot.nominal_beta, robot)
    mask = os.umask(0)
    os.umask(mask)
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~mask


def pose_csv(tmp_path, rows):
    path = tmp_path / 'poses.csv'
    save_poses(path, rows[:, 0], rows[:, 1:], KRANG_POSE_COLUMNS)
    return path


def test_truncated_pose_file(tmp_path, robot):
    rows = np.zeros((4, 17))
    rows[:, 0] = -1.5
    text = pose_csv(tmp_path, rows).read_text()
    cut = tmp_path / 'cut.csv'
    cut.write_text(text[: len(text) - 20])
    with pytest.raises(PoseFileError, match='line 5 has fewer values'):
        load_poses(cut, KRANG_POSE_COLUMNS)


def test_pose_outside_the_joint_limits(tmp_path, robot):
    rows = np.zeros((3, 17))
    rows[:, 0] = -1.5
    j = KRANG_POSE_COLUMNS.index('q_left_4')
    rows[1, 1 + j] = robot.upper[j] + 0.1
    path = pose_csv(tmp_path, rows)
    with pytest.raises(PoseFileError, match=r'line 3: q_left_4 = .* outside the joint limits'):
        load_poses(path, KRANG_POSE_COLUMNS, (robot.lower, robot.upper))
    load_poses(path, KRANG_POSE_COLUMNS)  # without limits the file itself is fine


def test_pose_whose_pitch_is_no_angle_is_refused_by_the_cli(tmp_path, capsys, robot):
    rows = np.zeros((3, 17))
    rows[:, 0] = -1.5
    rows[2, 0] = 1e308
    path = pose_csv(tmp_path, rows)
    with pytest.raises(PoseFileError, match=r'line 4: q_base = 1e\+308 rad is not a pitch'):
        load_poses(path, KRANG_POSE_COLUMNS)
    beta = save_beta(tmp_path / 'b.yaml', robot.nominal_beta, robot)
    code = krang(['evaluate', '--beta', str(beta), '--poses', str(path)])
    err = capsys.readouterr()
    lines = err.err.strip().splitlines()
    assert code != 0 and len(lines) == 1 and str(path) in lines[0] and 'q_base' in lines[0]
    assert 'Traceback' not in err.err and err.out == ''  # no partial output


def test_negative_row_is_refused(tmp_path, robot):
    path = save_beta(tmp_path / 'b.txt', robot.nominal_beta, robot)
    with pytest.raises(BetaFileError, match='--row -1 out of range'):
        load_beta(path, robot, row=-1)


def test_cli_bad_input_is_one_line_without_traceback(tmp_path, capsys, robot):
    rows = np.zeros((4, 17))
    rows[:, 0] = -1.5
    text = pose_csv(tmp_path, rows).read_text()
    cut = tmp_path / 'cut.csv'
    cut.write_text(text[:-20])
    beta = save_beta(tmp_path / 'b.yaml', robot.nominal_beta, robot)
    assert krang(['evaluate', '--beta', str(beta), '--poses', str(cut)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cut) in err[0] and 'Traceback' not in err[0]


@pytest.mark.parametrize(
    'content, message', [('', 'empty file'), ('header', '0 data rows'), ('nan', 'NaN or infinite')]
)
def test_discrepancy_bad_log_is_one_line_and_no_output(tmp_path, capsys, content, message):
    from krang_discrepancy.loaders import CSV_JOINT_COLUMNS

    header = [
        'dt_s',
        'i_cmd_left_A',
        'i_cmd_right_A',
        'dtheta_com_rad_s',
        'x_wheel_rad',
        'dx_wheel_rad_s',
        'q_base_rad',
        *CSV_JOINT_COLUMNS,
    ]
    rows = [['0.03'] + ['0.1'] * (len(header) - 1) for _ in range(10)]
    rows[4][2] = 'nan'
    text = {
        '': '',
        'header': ','.join(header) + '\n',
        'nan': '\n'.join(','.join(r) for r in [header] + rows) + '\n',
    }[content]
    path = tmp_path / 'log.csv'
    path.write_text(text)
    out = tmp_path / 'report'
    assert krang(['discrepancy', '--measured', str(path), '--out', str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and message in err[0], err
    assert not out.exists()
