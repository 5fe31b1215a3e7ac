"""krang poses pool | filter: the safe balanced pose pool and the meta-learning pose filter
(Algorithm 1)."""

import math
import sys
import time

import numpy as np

from .common import print_json


def register(subparsers):
    p = subparsers.add_parser(
        'poses',
        help='build the safe balanced pose pool, and filter it (meta-learning, Algorithm 1)',
        description='Pose sets for learning: `pool` draws random safe and balanced poses, '
        '`filter` picks the '
        "excitatory ones from a pool (the paper's Algorithm 1, or better criteria).",
    )
    sub = p.add_subparsers(dest='poses_command', metavar='<pool|filter>')

    pool = sub.add_parser(
        'pool',
        help='random safe and balanced poses',
        description="Draw random poses of the 16 body joints in the authors' pose-generator box "
        '(config/poses.yaml), balance each with the closed-form base pitch under the "real" beta '
        '(x_com = 0, CoM above the axle), keep those within the floor limits of the base pitch '
        'and '
        'free of self- and floor-collision (URDF collision shapes, pinocchio/coal; the floor is '
        'the '
        'plane z = -wheel_radius). Writes a pose CSV and prints {"poses", "seconds", "tries"} as '
        'the '
        'last line.',
    )
    pool.add_argument('--n', type=int, required=True, help='number of poses')
    pool.add_argument('--seed', type=int, default=0, help='random seed (default 0)')
    pool.add_argument('--out', required=True, help='pose CSV to write')
    pool.add_argument(
        '--beta',
        default=None,
        help='the "real" beta the poses are balanced under (default: the URDF)',
    )
    pool.add_argument('--row', type=int, default=None, help='row K of a multi-row .txt --beta')
    pool.add_argument(
        '--min-pitch',
        type=float,
        default=None,
        help='lowest balanced base pitch to accept (rad; default the floor limit of '
        'config/poses.yaml). '
        'For online sessions keep a margin above the caster (-1.763): the true robot balances '
        'up to ~0.2 rad away from the model, e.g. --min-pitch -1.45',
    )
    pool.add_argument('--no-progress', action='store_true', help='no progress bar')
    pool.add_argument(
        '--json', action='store_true', help='only the JSON line on stdout (it is printed anyway)'
    )
    pool.set_defaults(func=run_pool)

    flt = sub.add_parser(
        'filter',
        help='pick excitatory poses from a pool (Algorithm 1 and better criteria)',
        description="Meta-learning pose filter. Draws --n-betas erroneous betas (authors' recipe: "
        'masses kept, '
        'each m*x, m*y, m*z := v + U(-.5,.5) v + U(-.5,.5), |x_com(first pose)| > 2 cm), then '
        'repeats: '
        'choose the pose by the criterion, move every beta by the learner, until the chosen '
        "pose's error "
        '|phi*^T beta_k| < --tol for all k over the last --window poses. Criteria: paper-l1 = '
        'Algorithm 1 '
        'exactly (argmax_i sum_k |Phi_i^T beta_k|, GD step eta); squared = sum of squared errors; '
        'd-optimal = greedy D-optimal design (largest information gain log det) for the MAP '
        'estimator. '
        'Writes the chosen poses in order and prints {"selected", "seconds", "criterion"} as the '
        'last line.',
    )
    flt.add_argument('--pool', required=True, help='pool pose CSV (from `krang poses pool`)')
    flt.add_argument(
        '--n-betas', type=int, default=500, help='erroneous betas (default 500, as the paper)'
    )
    flt.add_argument('--seed', type=int, default=0, help='seed of the erroneous betas (default 0)')
    flt.add_argument('--tol', type=float, default=2e-3, help='x_tol in m (default 0.002)')
    flt.add_argument('--window', type=int, default=10, help='stop-rule window (default 10)')
    flt.add_argument(
        '--criterion',
        choices=('paper-l1', 'squared', 'd-optimal'),
        default='paper-l1',
        help='selection criterion (default paper-l1 = Algorithm 1)',
    )
    flt.add_argument(
        '--learner',
        choices=('gd', 'map'),
        default=None,
        help='how the betas move: gd (paper, default for paper-l1/squared) or map (default for '
        'd-optimal)',
    )
    flt.add_argument('--eta', type=float, default=300.0, help='GD step (default 300)')
    flt.add_argument(
        '--sigma-deg',
        type=float,
        default=0.1,
        help='pitch noise for d-optimal/map, deg (default 0.1)',
    )
    flt.add_argument(
        '--max-poses', type=int, default=None, help='stop after this many poses at the latest'
    )
    flt.add_argument('--beta', default=None, help='the "real" beta (default: the URDF)')
    flt.add_argument('--row', type=int, default=None, help='row K of a multi-row .txt --beta')
    flt.add_argument('--out', required=True, help='pose CSV of the chosen poses, in order')
    flt.add_argument('--no-progress', action='store_true', help='no progress bar')
    flt.add_argument(
        '--json', action='store_true', help='only the JSON line on stdout (it is printed anyway)'
    )
    flt.set_defaults(func=run_filter)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _real_beta(args, robot):
    from krang_model.beta import load_beta

    return robot.nominal_beta if args.beta is None else load_beta(args.beta, robot, row=args.row)


def run_pool(args):
    from tqdm import tqdm

    from krang_model.poses import save_poses
    from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
    from krang_pose_server.pool import PosePool

    if args.n <= 0:
        raise ValueError('--n must be positive')
    robot = load_krang()
    pool = PosePool(robot, _real_beta(args, robot))
    if args.min_pitch is not None:
        pool.q_base_limits = (args.min_pitch, pool.q_base_limits[1])
    bar = tqdm(
        total=args.n, unit='pose', file=sys.stderr, disable=args.no_progress, desc='pose pool'
    )
    res = pool.generate(args.n, seed=args.seed, progress=bar.update)
    bar.close()
    save_poses(args.out, res.q_base, res.joints, KRANG_POSE_COLUMNS)
    if not args.json:
        print(
            f'{args.n} safe balanced poses in {res.seconds:.1f} s ({res.tries} tries; rejected: '
            f'{res.rejected["floor_limits"]} base pitch outside the floor limits, '
            f'{res.rejected["collision"]} '
            f'in collision) -> {args.out}'
        )
    print_json({'poses': int(args.n), 'seconds': round(res.seconds, 3), 'tries': int(res.tries)})
    return 0


def run_filter(args):
    from tqdm import tqdm

    import krang_com_estimator as est
    from krang_model.com import phi
    from krang_model.poses import load_poses, save_poses
    from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
    from krang_pose_server.erroneous_betas import authors_betas
    from krang_pose_server.filtering import filter_poses

    robot = load_krang()
    real = _real_beta(args, robot)
    q_base, joints, _ = load_poses(args.pool, KRANG_POSE_COLUMNS)
    if len(q_base) == 0:
        raise ValueError(f'{args.pool}: no poses')
    t0 = time.perf_counter()
    Phi = phi(robot, q_base, joints)
    betas = authors_betas(real, args.n_betas, np.random.default_rng(args.seed), first_phi=Phi[0])
    kw = {}
    if args.criterion == 'd-optimal' or args.learner == 'map':
        prior = est.physical_prior_std(robot, real)
        A, b = est.equality_constraints(robot, robot.nominal_mass)
        _, kw['prior_cov'] = est.condition_on_constraints(real, np.diag(prior**2), A, b)
        z = est.pitch_sensitivity(robot, q_base, joints, real)
        kw['noise_var'] = (math.radians(args.sigma_deg) * z) ** 2 + 1e-12
    bar = tqdm(
        unit='pose', file=sys.stderr, disable=args.no_progress, desc=f'filter ({args.criterion})'
    )
    res = filter_poses(
        Phi,
        betas,
        args.criterion,
        eta=args.eta,
        x_tol=args.tol,
        window=args.window,
        max_poses=args.max_poses,
        learner=args.learner,
        progress=bar.update,
        **kw,
    )
    bar.close()
    seconds = time.perf_counter() - t0
    sel = res.selected
    save_poses(
        args.out,
        q_base[sel],
        joints[sel],
        KRANG_POSE_COLUMNS,
        extra={'pool_index': sel.tolist(), 'max_error_m': [f'{v:.6g}' for v in res.max_error]},
    )
    if not args.json:
        print(
            f'{args.criterion} ({res.learner}): {len(sel)} poses of {len(q_base)} '
            f'({"stop rule met" if res.converged else "stop rule NOT met"}: last {args.window} '
            f'errors '
            f'< {1000 * args.tol:g} mm for all {args.n_betas} betas) in {seconds:.2f} s -> '
            f'{args.out}'
        )
    print_json(
        {
            'selected': int(len(sel)),
            'seconds': round(seconds, 3),
            'criterion': args.criterion,
            'converged': bool(res.converged),
            'learner': res.learner,
        }
    )
    return 0
