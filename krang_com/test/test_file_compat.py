"""Files users keep still load: a beta file and a pose list written by krang_com 0.1.0 (test/data/;
the extended model and the bag have their own tests in test_discrepancy.py and
test_bag_writer_reader.py). The expected values are read from the files as plain YAML and CSV, not
through the loaders under test."""

import csv
from pathlib import Path

import numpy as np
import pytest
import yaml

from krang_model.beta import load_beta
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang

DATA = Path(__file__).resolve().parent / 'data'


@pytest.fixture(scope='module')
def robot():
    return load_krang()


def test_beta_file_of_version_1_loads(robot):
    doc = yaml.safe_load((DATA / 'beta_v1.yaml').read_text())
    expected = np.array([[b['m'], *b['m_com']] for b in doc['bodies']]).ravel()
    assert [b['name'] for b in doc['bodies']] == list(robot.body_names)
    beta = load_beta(DATA / 'beta_v1.yaml', robot)
    np.testing.assert_array_equal(beta, expected)
    assert beta.reshape(-1, 4)[:, 0].sum() == pytest.approx(doc['total_mass'], rel=1e-12)


def test_pose_list_of_version_1_loads(robot):
    with open(DATA / 'poses_v1.csv', newline='') as f:
        rows = list(csv.DictReader(f))
    q_base, joints, _ = load_poses(
        DATA / 'poses_v1.csv', KRANG_POSE_COLUMNS, (robot.lower, robot.upper)
    )
    np.testing.assert_array_equal(q_base, [float(r['q_base']) for r in rows])
    np.testing.assert_array_equal(
        joints, [[float(r[c]) for c in KRANG_POSE_COLUMNS] for r in rows]
    )
