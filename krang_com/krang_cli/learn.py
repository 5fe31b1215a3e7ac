"""krang learn: learn the mass model beta from balanced poses (batch or in the online order)."""

import math

import numpy as np

import krang_com_estimator as est
from krang_com_estimator.identifiability import determined_report
from krang_model.beta import load_beta, save_beta
from krang_model.com import x_com
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang

from .common import print_json


def register(subparsers):
    p = subparsers.add_parser(
        'learn',
        help='learn beta from balanced poses (paper GD or our MAP)',
        description=(
            'Learn the mass model beta (92 numbers: [m, m*x, m*y, m*z] per body) from balanced '
            'poses, '
            "starting from --beta0. Methods: paper-gd = the paper's gradient descent "
            'beta <- beta - eta (phi^T beta) phi, one pass in file order (eta = 300); '
            'paper-gd-mass = the '
            'same with the total mass held at the known value (Lagrange multiplier); map = '
            'Bayesian MAP with '
            'a physical prior around beta0 (masses +-10 percent, CoMs +-3 cm), the known total '
            'mass and wheel '
            'CoMs on the axle as hard constraints, the IMU/hand-balancing pitch noise, and the '
            'positive-mass '
            'and CoM-inside-the-link bounds enforced, every mass within --mass-spread of the '
            "URDF's and every CoM within --com-radius of CAD (batch); map-online = the same MAP, "
            'recursive, in file '
            "order (the com_estimator node's update); estimators registered by plug-ins are "
            'offered too (krang_com_estimator.register_estimator). Reports the k-fold '
            "cross-validated |x_com| on held-out records, how far each body's CoM and mass "
            'moved from beta0, which plausibility bounds the fit touches, and which directions '
            'of beta the data determine and which come from the prior.'
        ),
        epilog='Example (KIT = the real-data kit): krang learn '
        '--poses KIT/hardware_balanced_poses_train.csv '
        '--beta0 KIT/betas/betaVectors1initialBetahardwareAll190Vectors.txt --row 0 '
        '--out learned.yaml --method map',
    )
    p.add_argument(
        '--poses',
        required=True,
        help='pose CSV (q_base, q_waist, q_torso, q_left_1..7, q_right_1..7)',
    )
    p.add_argument(
        '--beta0',
        required=True,
        help="start/prior beta: authors' .txt (use --row) or our .yaml/.json",
    )
    p.add_argument(
        '--row',
        type=int,
        default=None,
        help='row K (from 0) of a multi-row .txt --beta0 (default 0)',
    )
    p.add_argument(
        '--out',
        required=True,
        help="learned beta: .txt = the authors' one-line format, "
        '.json = JSON, otherwise labelled YAML',
    )
    p.add_argument(
        '--method', choices=est.estimator_names(), default='map', help='estimator (default: map)'
    )
    p.add_argument('--eta', type=float, default=300.0, help='GD step of paper-gd* (default 300)')
    p.add_argument(
        '--sigma-imu-deg', type=float, default=0.1, help='IMU pitch noise, deg (default 0.1)'
    )
    p.add_argument(
        '--sigma-hand-rad',
        type=float,
        default=0.008,
        help='repeatability of hand balancing, rad (default 0.008: the scatter of the cancelled '
        'attempts of the real-data kit; use 0 for poses balanced by the controller)',
    )
    p.add_argument(
        '--mass-frac', type=float, default=0.1, help='MAP prior: relative mass std (default 0.1)'
    )
    p.add_argument(
        '--com-std', type=float, default=0.03, help='MAP prior: CoM std per axis, m (default 0.03)'
    )
    p.add_argument(
        '--total-mass',
        type=float,
        default=None,
        help='known total mass, kg (default: the URDF total, 162.158 kg)',
    )
    p.add_argument(
        '--mass-spread',
        type=float,
        default=est.MASS_SPREAD,
        metavar='FRAC',
        help="map: every body's mass stays within this fraction of the URDF's "
        f'(default {est.MASS_SPREAD}; 0 = no such bound)',
    )
    p.add_argument(
        '--com-radius',
        type=float,
        default=est.COM_RADIUS_M,
        metavar='M',
        help="map: every body's CoM stays within this distance of the CAD CoM, m "
        f'(default {est.COM_RADIUS_M}; 0 = no such bound)',
    )
    p.add_argument(
        '--calibrate',
        action='store_true',
        help='map: the pitch noise and the prior scales by evidence maximisation on '
        'the training poses, inside every fold of the cross-validation too '
        '(--sigma-*, --mass-frac and --com-std are then not used)',
    )
    p.add_argument(
        '--pitch-offset-std',
        type=float,
        default=None,
        metavar='RAD',
        help='map: also estimate an IMU pitch offset with this prior std (rad), '
        'reported with its posterior std',
    )
    p.add_argument(
        '--folds',
        type=int,
        default=10,
        help='k of the k-fold cross-validation (0 = skip; default 10)',
    )
    p.add_argument('--seed', type=int, default=0, help='seed of the fold split (default 0)')
    p.add_argument(
        '--json', action='store_true', help='print the summary as JSON on the last line'
    )
    p.set_defaults(func=run)


def run(args):
    robot = load_krang()
    beta0 = load_beta(args.beta0, robot, row=args.row)
    q_base, joints, _ = load_poses(args.poses, KRANG_POSE_COLUMNS, (robot.lower, robot.upper))
    if len(q_base) == 0:
        raise ValueError(f'{args.poses}: no poses')
    noise = est.NoiseModel(
        sigma_imu_rad=math.radians(args.sigma_imu_deg), sigma_hand_rad=args.sigma_hand_rad
    )
    kw = dict(
        noise=noise,
        mass_frac=args.mass_frac,
        com_std=args.com_std,
        total_mass=args.total_mass,
        eta=args.eta,
        calibrate=args.calibrate,
        pitch_offset_std=args.pitch_offset_std,
        mass_spread=args.mass_spread if args.mass_spread > 0 else None,
        com_radius=args.com_radius if args.com_radius > 0 else None,
    )
    estimator = est.make_estimator(args.method, robot, beta0, **kw)
    beta, info = estimator.fit(q_base, joints)
    offset = info.get('pitch_offset_rad', 0.0)  # the model sees the poses at q - offset
    xc0 = x_com(robot, q_base, joints, beta0)
    xc = x_com(robot, q_base - offset, joints, beta)
    cons = est.physical_consistency(
        robot,
        beta,
        total_mass=args.total_mass,
        mass_spread=kw['mass_spread'],
        com_radius=kw['com_radius'],
    )
    summary = {
        'method': args.method,
        'poses': int(len(q_base)),
        'out': str(args.out),
        'start_mean_abs_xcom_m': float(np.abs(xc0).mean()),
        'start_max_abs_xcom_m': float(np.abs(xc0).max()),
        'in_sample_mean_abs_xcom_m': float(np.abs(xc).mean()),
        'in_sample_max_abs_xcom_m': float(np.abs(xc).max()),
    }
    if args.folds and len(q_base) >= 2:
        pred, pitch = est.cross_validate(
            args.method, robot, q_base, joints, beta0, folds=args.folds, seed=args.seed, **kw
        )
        summary.update(
            {
                'cv_folds': int(min(args.folds, len(q_base))),
                'cv_mean_abs_xcom_m': float(np.abs(pred).mean()),
                'cv_max_abs_xcom_m': float(np.abs(pred).max()),
                'cv_mean_abs_pitch_deg': float(np.degrees(np.abs(pitch).mean())),
            }
        )
    summary.update(
        {
            'total_mass_kg': cons['total_mass'],
            'physically_consistent': cons['ok'],
            'violations': cons['violations'],
            'plausible_region': {
                'mass_spread': kw['mass_spread'],
                'com_radius_m': kw['com_radius'],
                'at_bound': cons['at_bound'],
            },
            'max_com_moved_m': max(bd['com_moved_m'] for bd in cons['bodies']),
            'com_moved_m': {bd['name']: bd['com_moved_m'] for bd in cons['bodies']},
            'mass_change_kg': {bd['name']: bd['mass_change_kg'] for bd in cons['bodies']},
            'mass_kg': {bd['name']: bd['mass'] for bd in cons['bodies']},
        }
    )
    if getattr(estimator, 'prior_std', None) is not None:
        rows, _, var = est.balanced_pose_rows(
            robot, q_base - offset, joints, beta, estimator.noise
        )
        summary['identifiability'] = determined_report(
            robot, estimator.prior_std, rows, var, estimator.A
        )
    cov = estimator.covariance
    if cov is not None:
        std = est.com_shift_std(robot, beta, cov)
        summary['com_moved_std_m'] = dict(zip(robot.body_names, (float(v) for v in std)))
    for key in ('calibration', 'pitch_offset_rad', 'pitch_offset_std_rad'):
        if key in info:
            summary[key] = info[key]
    save_beta(
        args.out,
        beta,
        robot,
        method=args.method,
        poses=str(args.poses),
        beta0=str(args.beta0),
        **{k: v for k, v in summary.items() if k.endswith('_m') or k in ('cv_folds',)},
    )
    if not args.json:
        _print_report(summary, info)
    if args.json:
        print_json(summary)
    return 0


def _print_report(s, info):
    print(f'{s["method"]}: learned from {s["poses"]} balanced poses -> {s["out"]}')
    print(
        f'  |x_com| start (beta0):   mean {100 * s["start_mean_abs_xcom_m"]:.2f} cm, '
        f'max {100 * s["start_max_abs_xcom_m"]:.2f} cm'
    )
    print(
        f'  |x_com| on the training poses: mean {100 * s["in_sample_mean_abs_xcom_m"]:.2f} cm, '
        f'max {100 * s["in_sample_max_abs_xcom_m"]:.2f} cm'
    )
    if 'cv_mean_abs_xcom_m' in s:
        print(
            f'  |x_com| cross-validated ({s["cv_folds"]}-fold, held-out records): mean '
            f'{100 * s["cv_mean_abs_xcom_m"]:.2f} cm, max {100 * s["cv_max_abs_xcom_m"]:.2f} cm '
            f'(balance pitch error {s["cv_mean_abs_pitch_deg"]:.2f} deg mean)'
        )
    print(
        f'  total mass {s["total_mass_kg"]:.3f} kg; physically consistent: '
        f'{"yes" if s["physically_consistent"] else "NO"}'
    )
    for v in s['violations']:
        print(f'    - {v}')
    region = s['plausible_region']
    if region['mass_spread'] is not None or region['com_radius_m'] is not None:
        spread = region['mass_spread']
        radius = region['com_radius_m']
        print(
            '  plausible region: masses '
            + (f"within {100 * spread:.0f} % of the URDF's" if spread is not None else 'free')
            + ', CoMs '
            + (f'within {100 * radius:.1f} cm of CAD' if radius is not None else 'free')
            + f'; largest CoM move {100 * s["max_com_moved_m"]:.2f} cm'
        )
        if region['at_bound']:
            print(
                '  at a bound (the data push beyond the plausible region there): '
                + ', '.join(region['at_bound'])
            )
    ident = s.get('identifiability')
    if ident:
        print(
            f'  the data determine {ident["determined_by_data"]} of {ident["directions"]} '
            f"directions of beta (their information at least the prior's); "
            f'{ident["from_prior"]} come from the prior'
        )
        print('    entries set by the data: ' + (', '.join(ident['entries_from_data']) or 'none'))
        if ident['entries_never_seen']:
            print('    never seen by the data: ' + ', '.join(ident['entries_never_seen']))
    if 'calibration' in s:
        c = s['calibration']
        print(
            f'  calibrated by evidence maximisation: pitch noise '
            f'{1000 * c["sigma_pitch_rad"]:.2f} mrad, prior mass std {100 * c["mass_frac"]:.1f} '
            f'%, CoM std '
            f'{100 * c["com_std_m"]:.2f} cm'
        )
    if 'pitch_offset_rad' in s:
        print(
            f'  IMU pitch offset {1000 * s["pitch_offset_rad"]:+.2f} +- '
            f'{1000 * s["pitch_offset_std_rad"]:.2f} mrad'
        )
    std = s.get('com_moved_std_m', {})
    print('  body        CoM moved [cm]  +- 1 std  mass change [kg]')
    for name, moved in s['com_moved_m'].items():
        sd = f'{100 * std[name]:8.2f}' if name in std else '       -'
        print(f'  {name:<10} {100 * moved:10.2f}  {sd} {s["mass_change_kg"][name]:14.3f}')
    if info.get('inequality_qp'):
        print('  (the Gaussian MAP left the plausible region; the constrained MAP was used)')
