"""krang evaluate: the x_com a beta predicts at each balanced pose (the paper's error measure)."""

import numpy as np

from krang_model.beta import load_beta
from krang_model.com import x_com
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS

from .common import print_json


def register(subparsers):
    p = subparsers.add_parser(
        'evaluate',
        help='x_com error of a beta over balanced poses',
        description='For each balanced pose, print x_com = phi(q)^T beta / M_nominal (m): the '
        'horizontal '
        'CoM offset from the axle that beta predicts where the real robot balanced (0 for a '
        'perfect model). Then the mean and max of |x_com| in cm.',
    )
    p.add_argument(
        '--beta', required=True, help="beta file: authors' .txt rows, or our .yaml/.json"
    )
    p.add_argument(
        '--row',
        type=int,
        default=None,
        help='row K (from 0) of a multi-row .txt beta file (default 0)',
    )
    p.add_argument(
        '--poses',
        required=True,
        help='pose CSV (columns q_base, q_waist, q_torso, q_left_1..7, '
        'q_right_1..7; extra columns ignored)',
    )
    p.add_argument(
        '--json', action='store_true', help='print only the summary as JSON on the last line'
    )
    p.set_defaults(func=run)


def run(args):
    from krang_model.robot import load_krang

    robot = load_krang()
    beta = load_beta(args.beta, robot, row=args.row)
    q_base, joints, _ = load_poses(args.poses, KRANG_POSE_COLUMNS, (robot.lower, robot.upper))
    if len(q_base) == 0:
        raise ValueError(f'{args.poses}: no poses')
    xc = x_com(robot, q_base, joints, beta)
    summary = {
        'mean_abs_xcom_m': float(np.abs(xc).mean()),
        'max_abs_xcom_m': float(np.abs(xc).max()),
        'n': int(len(xc)),
    }
    if args.json:
        print_json(summary)
        return 0
    print('pose  x_com_m')
    for i, v in enumerate(xc):
        print(f'{i:4d}  {v:+.6f}')
    print(
        f'mean |x_com| = {100 * summary["mean_abs_xcom_m"]:.2f} cm, max |x_com| = '
        f'{100 * summary["max_abs_xcom_m"]:.2f} cm over {summary["n"]} poses'
    )
    return 0
