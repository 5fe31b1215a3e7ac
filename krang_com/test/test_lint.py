"""Lint: ruff over the checkout (the package and bench/) with ruff.toml (ROS's 99 columns,
ament_flake8's E, F and W checks), in the default run like ament_flake8 in a colcon test."""

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip('ruff', reason='ruff is in the test extras: pip install -e .[test]')

REPO = Path(__file__).resolve().parents[2]  # the checkout: krang_com/, bench/


def test_ruff_finds_no_violations():
    result = subprocess.run(
        [
            sys.executable,
            '-m',
            'ruff',
            'check',
            '--config',
            str(REPO / 'ruff.toml'),
            '--output-format',
            'concise',
            '--no-cache',
            str(REPO),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert result.returncode == 0, f'ruff found violations:\n{result.stdout}{result.stderr}'
