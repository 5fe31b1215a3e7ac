"""krang relearn: replay the balanced poses of a bag through an estimator, offline."""

import numpy as np

from krang_bag.relearn import relearn
from krang_com_estimator import estimator_names
from krang_model.beta import load_beta, save_beta
from krang_model.robot import load_krang

from .common import print_json

# The online betas travel as float64 (CDR), and the replay runs the same code on the same poses. It
# is not bit-identical: numpy's SIMD kernels may group a sum differently with the arrays' memory
# alignment, and the MAP solve amplifies those last-bit differences by its condition number
# (measured after a 3-pose demo: 1.8e-9 on a beta element of 75.8, i.e. 2.3e-11 relative). So the
# replay must agree to 9 significant digits of the largest beta element.
REPRODUCTION_TOLERANCE = 1e-9


def register(subparsers):
    p = subparsers.add_parser(
        'relearn',
        help='re-learn beta from the balanced poses in a bag',
        description='Reads every /balanced_pose of an MCAP bag and runs them, in order, through '
        'an '
        'estimator starting from the first beta the online estimator published (or --beta0). '
        'With the online method (default map-online) this reproduces the online beta; '
        'choose --method to try another estimator on the same data.',
    )
    p.add_argument(
        'bag', help='MCAP bag recorded by mcap_recorder (e.g. a krang demo session.mcap)'
    )
    p.add_argument(
        '--out',
        required=True,
        help="beta file to write (.txt: authors' one-line format; .yaml/.json)",
    )
    p.add_argument(
        '--method',
        default='map-online',
        choices=estimator_names(),
        help='a registered estimator (default map-online, the online one)',
    )
    p.add_argument(
        '--beta0', default=None, help="initial beta file instead of the bag's first published beta"
    )
    p.add_argument('--row', type=int, default=None, help='row of a multi-row .txt --beta0')
    p.add_argument('--json', action='store_true', help='print a JSON summary as the last line')
    p.set_defaults(func=run)


def run(args):
    robot = load_krang()
    beta0 = load_beta(args.beta0, robot, row=args.row) if args.beta0 else None
    result = relearn(args.bag, robot, args.method, beta0)
    save_beta(
        args.out,
        result.beta,
        robot,
        method=args.method,
        poses=result.rest_poses,
        source=str(args.bag),
    )
    deviation = result.relative_deviation
    moving = len(result.poses) - result.rest_poses
    summary = {
        'poses': result.rest_poses,
        'points_while_moving': moving,
        'method': args.method,
        'out': str(args.out),
        'online_betas': int(len(result.recorded)),
        'max_rel_diff_to_online': None if np.isnan(deviation) else deviation,
    }
    if args.json:
        print_json(summary)
    else:
        print(
            f'{result.rest_poses} balanced poses and {moving} points read while moving replayed '
            f'with {args.method}; beta written to {args.out}'
        )
        if not np.isnan(deviation):
            verdict = 'reproduces' if deviation <= REPRODUCTION_TOLERANCE else 'differs from'
            print(
                f'largest difference to the {len(result.recorded)} betas published online: '
                f'{deviation:.3g} of the '
                f'largest beta element ({verdict} the online run within '
                f'{REPRODUCTION_TOLERANCE:g})'
            )
    return 0
