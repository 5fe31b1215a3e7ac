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
    repo = Path(__file__).resolve().parents[1]
    p = Path(env) if env else repo.parent / 'shared' / 'krang_data'
    return p if (p / 'poses' / 'finalSetMunzir.txt').exists() else None


def load_filtered_poses(kit):
    """(poses (528, 16) pose order, authors' training order (filtered indices) or None,
    description) from poses/finalSetMunzir.txt (Munzir format: heading, q_base, x, y, z, q_lwheel,
    q_rwheel, q_waist, q_torso, q_kinect, left 1..7, right 1..7; the Kinect is dropped)."""
    kit = Path(kit)
    raw = np.loadtxt(kit / 'poses' / 'finalSetMunzir.txt', ndmin=2)
    if raw.shape[1] != 24:
        raise ValueError(
            f'{kit}/poses/finalSetMunzir.txt: expected 24 columns, got {raw.shape[1]}'
        )
    poses = raw[:, [7, 8] + list(range(10, 24))]
    order = None
    train = kit / 'hardware_balanced_poses_train.csv'
    if train.exists():
        with open(train, newline='') as f:
            rows = list(csv.DictReader(f))
        rows.sort(key=lambda r: int(r['train_order']))
        order = [int(r['filtered_pose_index']) for r in rows]
    return poses, order, f'{kit}/poses/finalSetMunzir.txt'


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
