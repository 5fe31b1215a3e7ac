"""krang identifiability: which parts of the mass model balanced poses can and cannot fix."""

from .common import print_json


def register(subparsers):
    p = subparsers.add_parser(
        'identifiability',
        help='rank and base parameters of the CoM regressor, in words',
        description='Stacks phi(q) over many random configurations (balanced poses, and arbitrary '
        'base pitch for '
        'comparison), finds its rank and base parameters by QR with column pivoting (Gautier & '
        'Khalil), '
        'and prints which beta entries the data can never fix (phi always 0), which only in '
        'combination with others, and why balanced poses cannot fix the scale of the mass moments '
        '(the known total mass does not help: the Base and wheel masses never appear in phi).',
    )
    p.add_argument('--n', type=int, default=2000, help='random configurations (default 2000)')
    p.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    p.add_argument(
        '--pool', default=None, help='use the joints of this pose CSV instead of uniform samples'
    )
    p.add_argument('--json', action='store_true', help='print the result as JSON on the last line')
    p.set_defaults(func=run)


def run(args):
    from krang_com_estimator.identifiability import analyse
    from krang_model.poses import load_poses
    from krang_model.robot import KRANG_POSE_COLUMNS, load_krang

    robot = load_krang()
    pool = None
    if args.pool:
        q, j, _ = load_poses(args.pool, KRANG_POSE_COLUMNS)
        pool = (q, j)
    res = analyse(robot, n=args.n, seed=args.seed, pool=pool)
    if args.json:
        print_json({k: v for k, v in res.items() if k != 'lines'})
    else:
        print('\n'.join(res['lines']))
    return 0
