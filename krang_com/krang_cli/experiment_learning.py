"""krang experiment learning (mounted by krang_cli/experiment.py; standalone: experiment-learning):
the paper's simulation redone, learning curves and the real data (krang_experiments.learning)."""

import sys

from .common import print_json


def _add_arguments(p):
    p.add_argument(
        '--out',
        required=True,
        help='output folder (learning_results.json, learning_curves.png, real_data.png)',
    )
    p.add_argument(
        '--data',
        default=None,
        help='real-data kit folder (krang_data) for the hardware part and the '
        "authors' pool check; skipped without it",
    )
    p.add_argument(
        '--pool', type=int, default=20000, help='pool size (default 20000, as the paper)'
    )
    p.add_argument(
        '--n-betas', type=int, default=500, help='erroneous betas for Algorithm 1 (default 500)'
    )
    p.add_argument(
        '--runs', type=int, default=50, help='simulated learning runs per method (default 50)'
    )
    p.add_argument(
        '--test', type=int, default=1000, help='held-out poses for the CoM error (default 1000)'
    )
    p.add_argument(
        '--sigma-deg',
        type=float,
        default=0.1,
        help='IMU pitch noise in the simulation (default 0.1)',
    )
    p.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    p.add_argument(
        '--json', action='store_true', help='print the headline numbers as JSON on the last line'
    )
    p.set_defaults(func=run)


_DESCRIPTION = (
    "Reproduces the paper's simulation (Algorithm 1 on a pool of 20,000 poses with 500 erroneous "
    'betas, '
    'x_tol = 2 mm: filtered poses versus random order), learning curves with 0.1 deg IMU noise '
    '(paper-GD on the '
    'filtered poses, paper-GD on random poses, our MAP on D-optimal poses; error = the horizontal '
    'CoM error '
    'against the hidden true beta at 1000 held-out poses, and the CoM position error), and, with '
    '--data, the '
    'real hardware data (k-fold CV of |x_com| on the 189 hand-balanced records, poses needed, '
    'physical '
    'consistency). About a minute on 2 cores.'
)


def register(subparsers):
    """`krang experiment-learning ...` (top level)."""
    _add_arguments(
        subparsers.add_parser(
            'experiment-learning',
            help='learning experiments (paper sim, curves, real data)',
            description=_DESCRIPTION,
        )
    )


def register_experiment(experiment_subparsers):
    """`krang experiment learning ...`, for a `krang experiment` command group."""
    _add_arguments(
        experiment_subparsers.add_parser(
            'learning',
            help='learning experiments (paper sim, curves, real data)',
            description=_DESCRIPTION,
        )
    )


def run(args):
    from krang_experiments import learning  # at run time: it loads the pose pool and matplotlib

    params = learning.Params(
        data_dir=args.data,
        n_pool=args.pool,
        n_betas=args.n_betas,
        n_runs=args.runs,
        n_test=args.test,
        sigma_deg=args.sigma_deg,
        seed=args.seed,
    )
    result = learning.run(
        params, progress=(lambda m: print(m, file=sys.stderr)) if args.json else print
    )
    learning.report(result, args.out)
    head = headline(result['results'])
    if not args.json:
        for k, v in head.items():
            print(f'{k}: {v}')
        print(
            f'results: {args.out}/learning_results.json, figures: {args.out}/learning_curves.png'
            + (f', {args.out}/real_data.png' if args.data else '')
        )
    else:
        print_json(head)
    return 0


def headline(res):
    out = {}
    pf = res.get('paper_filter')
    if pf:
        out['filtered_poses'] = pf['filtered_poses']
        out['random_order_poses_same_stop_rule'] = pf['random_order_poses']
        out['random_order_poses_to_match_pool_worst_error'] = pf['pool_wide'][
            'random_poses_to_match'
        ]
        out['filter_seconds'] = round(pf['seconds'], 2)
    if 'poses_to_1mm' in res:
        out['poses_to_1mm_balance_error'] = res['poses_to_1mm']
    rd = res.get('real_data')
    if rd:
        cv = rd['cross_validation']
        out['real_cv_mean_cm'] = {k: round(v['mean_cm'], 3) for k, v in cv.items()}
        out['real_cv_max_cm'] = {k: round(v['max_cm'], 2) for k, v in cv.items()}
        out['real_map_records_to_reach_gd_final'] = rd['learning_curve'][
            'map_records_to_reach_gd_final'
        ]
        out['real_learned_physically_consistent'] = rd['learned']['physically_consistent']
    if 'authors_pool' in res:
        out['authors_pool_6003_filtered_poses'] = res['authors_pool'][
            'authors_pool_6003_filtered_poses'
        ]
    return out
