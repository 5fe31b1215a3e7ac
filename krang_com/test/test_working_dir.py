"""krang_cli.processes.WorkingDir: a benchmark's temporary directory goes after a normal run and
stays, named, after a failure or an invalid run."""

import os

import pytest

from krang_cli.processes import WorkingDir


def test_removed_after_a_normal_run():
    with WorkingDir('krang_test_') as work:
        open(os.path.join(work.path, 'log'), 'w').close()
        path = work.path
    assert not os.path.exists(path)


def test_kept_and_named_when_the_run_fails(capsys):
    with pytest.raises(RuntimeError, match='player did not start'):
        with WorkingDir('krang_test_') as work:
            raise RuntimeError('player did not start')
    assert os.path.isdir(work.path)
    assert work.path in capsys.readouterr().err
    os.rmdir(work.path)


def test_kept_and_named_when_the_run_is_not_valid(capsys):
    with WorkingDir('krang_test_') as work:
        work.keep('NOT VALID')
    assert os.path.isdir(work.path)
    assert f'NOT VALID: logs and records kept in {work.path}' in capsys.readouterr().err
    os.rmdir(work.path)
