"""Helpers shared by the experiments: the real-data kit, the filtered poses, the simulated
robot."""

import csv
import math
import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from krang_adrc_controller.controller import load_controller_config
from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.robot import load_krang


def kit_dir(path=None):
    """The real-data kit: `path`, else $KRANG_DATA, else shared/krang_data beside the checkout; or
    None when there is none (the experiments then fall back to generated poses)."""
    if path:
        p = Path(path)
        return p if p.exists() else None
    env = os.environ.get('KRANG_DATA')
    checkout = Path(__file__).resolve().parents[2]  # krang_com/<package>/common.py
    p = Path(env) if env else checkout.parent / 'shared' / 'krang_data'
    return p if (p / 'poses' / 'finalSetMunzir.txt').exists() else None


def load_filtered_poses(kit):
    """(poses (528, 16) pose order, authors' training order (filtered indices) or None,
    description) from poses/finalSetMunzir.txt (load_authors_poses; the Kinect is dropped)."""
    kit = Path(kit)
    path = kit / 'poses' / 'finalSetMunzir.txt'
    _, poses = load_authors_poses(path)
    order = None
    train = kit / 'hardware_balanced_poses_train.csv'
    if train.exists():
        with open(train, newline='') as f:
            rows = list(csv.DictReader(f))
        rows.sort(key=lambda r: int(r['train_order']))
        order = [int(r['filtered_pose_index']) for r in rows]
    return poses, order, f'{kit}/poses/finalSetMunzir.txt'


def load_authors_poses(path):
    """(q_base, joints (N, 16)) from the authors' pose files: Munzir format (24 columns: heading,
    q_base, x, y, z, wheels, waist, torso, kinect, arms) or old DART format (25 columns:
    axis-angle, x, y, z, wheels, waist, torso, kinect, arms; q_base by the rule of
    krang_data/README.md)."""
    data = np.loadtxt(path, ndmin=2)
    if data.shape[1] == 24:
        q_base = data[:, 1]
        rest = data[:, 7:]
    elif data.shape[1] == 25:
        q_base = np.array([_dart_q_base(aa) for aa in data[:, :3]])
        rest = data[:, 8:]
    else:
        raise ValueError(f'{path}: {data.shape[1]} columns, expected 24 (Munzir) or 25 (DART)')
    joints = np.column_stack([rest[:, 0:2], rest[:, 3:17]])  # drop q_kinect
    return q_base, joints


def _dart_q_base(aa):
    angle = np.linalg.norm(aa)
    if angle < 1e-15:
        R = np.eye(3)
    else:
        k = aa / angle
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    h = math.atan2(R[0, 0], -R[1, 0])
    q = math.atan2(R[0, 1] * math.cos(h) + R[1, 1] * math.sin(h), R[2, 1])
    return (q - math.pi + math.pi) % (2 * math.pi) - math.pi


def setup(true_beta=None, params=None):
    """(robot, hidden true beta, controller configuration): defaults config/sim_true_beta.yaml and
    config/controller.yaml."""
    robot = load_krang()
    beta = load_beta(true_beta or config_path('sim_true_beta.yaml'), robot)
    cfg = load_controller_config(params) if params else load_controller_config()
    return robot, beta, cfg


def mean_std(values):
    """(mean, population std) of the finite values, or (None, None)."""
    v = np.asarray(
        [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))],
        float,
    )
    if v.size == 0:
        return None, None
    return float(v.mean()), float(v.std())  # population std (ddof=0), as the paper's table


def fmt(m, s, digits=3):
    if m is None:
        return 'n/a'
    return f'{m:.{digits}g} ± {s:.2g}'


def subplots(*args, figsize, **kw):
    """pyplot.subplots without pyplot: a Figure that draws with Agg whatever the session's backend,
    and needs no closing."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*args, **kw)
