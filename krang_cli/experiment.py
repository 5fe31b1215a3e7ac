"""krang experiment: the paper's experiments in closed-loop simulation.

Sub-subcommands are registered in ``EXPERIMENTS``; adding one is a small function pair::

    from krang_cli.experiment import register_experiment
    def _args(p): p.add_argument('--out', default='out/mine')
    def _run(args): ...; return 0
    register_experiment('mine', 'one-line help', _args, _run)

Modules named ``krang_cli/experiment_*.py`` are imported when the parser is built, so another
engineer's file can register its experiments this way without touching this one; such a module may
instead define ``register_experiment(experiment_subparsers)`` and add its own sub-subparser (as
``experiment_learning.py`` does for ``krang experiment learning``).

Built in:
* ``table2``: Table II in simulation. Online learning (paper GD, step 300) on the simulated robot over
  the kit's filtered poses, then 7 stand-up-and-balance runs (noise seeds 0..6) per learned beta in the
  Table II pose, plus beta_0 and the TRUE beta; the paper's and physical metrics, power traces,
  learning curve.
* ``adrc-vs-lqr``: ADRC and plain LQR with the same wrong CoM (2.5 cm): stand-up, push, pose change.
"""
from __future__ import annotations

import argparse
import csv
import importlib
import json
import math
import pkgutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .common import print_json

# ----------------------------------------------------------------------------- registry


@dataclass
class Experiment:
    name: str
    help: str
    add_arguments: Callable
    run: Callable
    description: str | None = None


EXPERIMENTS: dict[str, Experiment] = {}


def register_experiment(name, help, add_arguments, run, description=None):
    """Add `krang experiment NAME`: add_arguments(parser) declares options, run(args) -> exit code."""
    EXPERIMENTS[name] = Experiment(name, help, add_arguments, run, description)


def _discover():
    """Import krang_cli/experiment_*.py (they may call register_experiment at import) and return them."""
    import sys
    import krang_cli
    found = []
    for mod in sorted(pkgutil.iter_modules(krang_cli.__path__), key=lambda m: m.name):
        if mod.name.startswith('experiment_'):
            try:
                found.append(importlib.import_module(f'krang_cli.{mod.name}'))
            except Exception as err:   # one broken plug-in must not take `krang experiment` down
                print(f'krang experiment: skipped krang_cli.{mod.name} ({err})', file=sys.stderr)
    return found


def register(subparsers):
    p = subparsers.add_parser('experiment', help="the paper's experiments in closed-loop simulation",
                              description=__doc__.split('\n\n')[0] + ' Run `krang experiment <name> --help`.')
    sub = p.add_subparsers(dest='experiment', metavar='<experiment>')
    plugins = _discover()
    for exp in EXPERIMENTS.values():
        sp = sub.add_parser(exp.name, help=exp.help, description=exp.description or exp.help,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
        exp.add_arguments(sp)
        sp.set_defaults(func=exp.run)
    # second protocol: a module-level hook `register_experiment(experiment_subparsers)` that adds its own
    # sub-subparsers (e.g. krang_cli/experiment_learning.py -> `krang experiment learning`)
    for mod in plugins:
        hook = getattr(mod, 'register_experiment', None)
        if callable(hook) and hook is not register_experiment:
            hook(sub)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


# ----------------------------------------------------------------------------- shared helpers


def kit_dir(path=None):
    """The real-data kit ($KRANG_DATA, else ../shared/krang_data next to the checkout), or None."""
    import os
    if path:
        p = Path(path)
        return p if p.exists() else None
    env = os.environ.get('KRANG_DATA')
    repo = Path(__file__).resolve().parents[1]
    p = Path(env) if env else repo.parent / 'shared' / 'krang_data'
    return p if (p / 'poses' / 'finalSetMunzir.txt').exists() else None


def load_filtered_poses(kit):
    """(poses (528, 16) pose order, authors' training order (filtered indices) or None, description)
    from poses/finalSetMunzir.txt (Munzir format: heading, q_base, x, y, z, q_lwheel, q_rwheel,
    q_waist, q_torso, q_kinect, left 1..7, right 1..7; the Kinect is dropped)."""
    kit = Path(kit)
    raw = np.loadtxt(kit / 'poses' / 'finalSetMunzir.txt', ndmin=2)
    if raw.shape[1] != 24:
        raise ValueError(f'{kit}/poses/finalSetMunzir.txt: expected 24 columns, got {raw.shape[1]}')
    poses = raw[:, [7, 8] + list(range(10, 24))]
    order = None
    train = kit / 'hardware_balanced_poses_train.csv'
    if train.exists():
        with open(train, newline='') as f:
            rows = list(csv.DictReader(f))
        rows.sort(key=lambda r: int(r['train_order']))
        order = [int(r['filtered_pose_index']) for r in rows]
    return poses, order, f'{kit}/poses/finalSetMunzir.txt'


def _setup(args):
    from krang_adrc_controller.controller import load_controller_config
    from krang_model.beta import load_beta
    from krang_model.config import config_path
    from krang_model.robot import load_krang
    robot = load_krang()
    true_beta = load_beta(args.true_beta or config_path('sim_true_beta.yaml'), robot)
    cfg = load_controller_config(args.params) if getattr(args, 'params', None) else load_controller_config()
    return robot, true_beta, cfg


def _mean_std(values):
    v = np.asarray([x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))], float)
    if v.size == 0:
        return None, None
    return float(v.mean()), float(v.std())          # population std (ddof=0), as the paper's table


def _fmt(m, s, digits=3):
    if m is None:
        return 'n/a'
    return f'{m:.{digits}g} ± {s:.2g}'


# ----------------------------------------------------------------------------- adrc-vs-lqr


def adrc_vs_lqr_scenario(robot, true_beta, beta_est, disturbance_rejection=True, *, seed=0, seconds=70.0,
                         config=None, kick_at_s=25.0, kick_rad_s=0.3, pose_at_s=45.0, pose2=None,
                         eso_omega_o=None):
    """Stand up from the caster (enable at 0.5 s), balance; at `kick_at_s` a push (+kick_rad_s on the
    body's pitch rate); at `pose_at_s` the waist opens from 2.755 to 2.3 rad. Per phase: rest position
    (mean of the last 3 s) and the prediction x_ref - F_th0 delta / F_x0, max excursion from the rest,
    overshoot, settle time (2 cm band), max tilt from the true balance pitch, peak/RMS current."""
    from krang_adrc_controller.controller import load_controller_config
    from krang_sim.closed_loop import TABLE2_POSE, ClosedLoop, Disturbance
    over = {'use_disturbance_rejection': bool(disturbance_rejection)}
    if eso_omega_o is not None:
        over['eso_omega_o'] = float(eso_omega_o)
    cfg = (config or load_controller_config()).replace(**over)
    if pose2 is None:
        pose2 = TABLE2_POSE.copy()
        pose2[0] = 2.3
    loop = ClosedLoop(robot, true_beta, beta_est, TABLE2_POSE, controller_config=cfg, seed=seed, log_rate_hz=100.0)
    loop.schedule(Disturbance(kick_at_s, 'kick', kick_rad_s), Disturbance(pose_at_s, 'joints', pose2))
    ctl = loop.controller
    bounds = [(0.5, kick_at_s, 'stand-up'), (kick_at_s, pose_at_s, 'push'), (pose_at_s, seconds, 'pose change')]
    loop.run(0.5)
    ctl.set_enabled(True)
    phases = []
    for t0, t1, name in bounds:
        loop.run(t1 - loop.sim.t)
        delta = ctl.com_offset + loop.sim.balance_pitch()
        pred = ctl.x_ref + ctl.expected_rest_offset() * delta if ctl.design else math.nan
        phases.append({'name': name, 't0': t0, 't1': t1, 'theta_error_rad': delta, 'x_rest_predicted_m': pred,
                       'balance_trim_rad': ctl.last_output.balance_trim})
    lg = {k: np.asarray(v, float) for k, v in loop.log.items()}
    t, x, q, i = lg['t'], lg['x_true_m'], lg['q_base_true'], lg['i_left']
    t_bal = next((tt for tt, e in loop.events if '->balance' in e), math.nan)
    for k, ph in enumerate(phases):
        m = (t >= ph['t0']) & (t < ph['t1'])
        xr = float(x[m & (t >= ph['t1'] - 3.0)].mean())
        ph['x_rest_m'] = xr
        dev = x[m] - xr
        ph['max_excursion_m'] = float(np.abs(dev).max())
        x_start = x[m][0]
        sgn = math.copysign(1.0, xr - x_start) if abs(xr - x_start) > 1e-3 else 1.0
        ph['overshoot_m'] = float(max(0.0, (sgn * dev).max()))
        out = np.flatnonzero(np.abs(dev) > 0.02)
        ph['settle_time_s'] = float(t[m][out[-1]] - ph['t0']) if out.size else 0.0
        # tilt from the (instantaneous) true balance pitch; stand-up: from BALANCE entry on
        mt = m & (t >= (t_bal if k == 0 else ph['t0']))
        ph['max_tilt_from_balance_rad'] = float(np.abs(q[mt] - lg['balance_pitch_true'][mt]).max()) \
            if mt.any() else math.nan
        ph['peak_current_a'] = float(np.abs(i[m]).max())
        ph['rms_current_a'] = float(np.sqrt(np.mean(i[m] ** 2)))
        rest = m & (t >= ph['t1'] - 5.0)
        ph['rest_current_std_a'] = float(i[rest].std())
    times = {}
    for tt, e in loop.events:
        if '->' in e:
            times.setdefault(e.split('->', 1)[1].split(':', 1)[0], tt)
    return {'stood_up': 'balance' in times, 'final_mode': ctl.mode.value, 'mode_times': times,
            'phases': phases, 'log': lg, 'expected_rest_per_rad_m': ctl.expected_rest_offset()}


def _adrc_args(p):
    p.add_argument('--out', default='out/adrc_vs_lqr', help='output folder (report.md, PNG, JSON)')
    p.add_argument('--shift', type=float, default=0.025, help='CoM error of the wrong beta in m (default 0.025)')
    p.add_argument('--seed', type=int, default=5)
    p.add_argument('--true-beta', default=None, help='hidden truth (default config/sim_true_beta.yaml)')
    p.add_argument('--params', default=None, help='controller YAML (default config/controller.yaml)')
    p.add_argument('--json', action='store_true', help='print a JSON summary as the last stdout line')


def _run_adrc(args):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from krang_sim.closed_loop import TABLE2_POSE, shifted_beta
    robot, true_beta, cfg = _setup(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    wrong = shifted_beta(robot, true_beta, TABLE2_POSE, args.shift)
    paper = cfg.replace(balance_point_observer=False)
    observer = cfg.replace(balance_point_observer=True)
    variants = [('ADRC + balance-point observer (shipped)', wrong, True, None, observer),
                ("ADRC, the paper's law (ESO 20 rad/s)", wrong, True, None, paper),
                ('plain LQR', wrong, False, None, paper),
                ("ADRC, the paper's law (authors' ESO gains)", wrong, True, 0.0, paper),
                ('plain LQR, TRUE beta', true_beta, False, None, paper)]
    results = {}
    wall = time.perf_counter()
    for name, beta, dr, omega, variant_cfg in variants:
        results[name] = adrc_vs_lqr_scenario(robot, true_beta, beta, dr, seed=args.seed, config=variant_cfg,
                                             eso_omega_o=omega)
    wall = time.perf_counter() - wall
    fig, ax = plt.subplots(3, 1, figsize=(11, 9), sharex=True)
    styles = ['C3-', 'C0-', 'C1--', 'C2:', 'k-']
    for (name, res), st in zip(results.items(), styles):
        lg = res['log']
        ax[0].plot(lg['t'], lg['x_true_m'], st, lw=1.2, label=name)
        ax[1].plot(lg['t'], lg['q_base_true'], st, lw=1.0, label=name)
        ax[2].plot(lg['t'], lg['i_left'], st, lw=0.7, label=name)
    for a in ax:
        for tt in (25.0, 45.0):
            a.axvline(tt, color='grey', lw=0.6)
    ax[0].set_ylabel('x (m, ground truth)')
    ax[1].set_ylabel('true base pitch (rad)')
    ax[2].set_ylabel('left current (A)')
    ax[2].set_xlabel('t (s): enable at 0.5 s, push at 25 s, waist 2.755 -> 2.3 rad at 45 s')
    ax[0].legend(loc='lower left', fontsize=8)
    ax[0].set_title(f'Wrong CoM ({100 * args.shift:.1f} cm in the Table II pose): ADRC (with and without the '
                    f'balance-point observer) vs plain LQR')
    fig.tight_layout()
    fig.savefig(out / 'adrc_vs_lqr.png', dpi=110)
    plt.close(fig)
    summary = {name: {'stood_up': r['stood_up'], 'final_mode': r['final_mode'],
                      'phases': [{k: v for k, v in ph.items()} for ph in r['phases']]}
               for name, r in results.items()}
    lines = [f'# ADRC vs plain LQR with a wrong CoM ({100 * args.shift:.1f} cm)', '',
             f'`krang experiment adrc-vs-lqr --out {args.out}` (seed {args.seed}; {wall:.1f} s wall).',
             'Robot: simulated Krang, hidden truth `config/sim_true_beta.yaml`; the controller uses the truth with '
             f'the Base mass moment shifted so the paper\'s x_com is off by {100 * args.shift:.1f} cm in the Table II '
             'pose (theta error ' f'{results["plain LQR"]["phases"][0]["theta_error_rad"]:.3f} rad). Sensor noise on. '
             'Stand-up uses the hardware stand PD in every variant; the compared law acts from BALANCE on. '
             'The balance-point observer (krang_adrc_controller/balance_point.py) estimates the CoM-angle error '
             'delta from the theta-channel disturbance and the ADRC regulates about it; its estimate at the end of '
             'each phase is the last column.', '',
             '![adrc vs lqr](adrc_vs_lqr.png)', '',
             '| controller | phase | rest x (m) | LQR offset -F_th0 δ/F_x0 (m) | max excursion (m) | overshoot (m) | '
             'settle 2 cm (s) | max tilt (rad) | peak I (A) | I std at rest (A) | δ (rad) | observer δ̂ (rad) |',
             '|---|---|---|---|---|---|---|---|---|---|---|---|']
    for name, r in results.items():
        for ph in r['phases']:
            lines.append(f"| {name} | {ph['name']} | {ph['x_rest_m']:.3f} | {ph['x_rest_predicted_m']:.3f} | "
                         f"{ph['max_excursion_m']:.3f} | {ph['overshoot_m']:.3f} | {ph['settle_time_s']:.1f} | "
                         f"{ph['max_tilt_from_balance_rad']:.3f} | {ph['peak_current_a']:.1f} | "
                         f"{ph['rest_current_std_a']:.2f} | {ph['theta_error_rad']:.4f} | {ph['balance_trim_rad']:.4f} |")
    (out / 'report.md').write_text('\n'.join(lines) + '\n')
    (out / 'summary.json').write_text(json.dumps(summary, indent=1))
    print('\n'.join(lines))
    if args.json:
        print_json({'out': str(out), 'variants': summary})
    return 0


register_experiment('adrc-vs-lqr', 'ADRC vs plain LQR with the same wrong CoM (stand-up, push, pose change)',
                    _adrc_args, _run_adrc)


# ----------------------------------------------------------------------------- table2

PAPER_TABLE2 = {   # the paper's Table II (mean, std)
    16: ((4.70, 0.16), (2.49, 0.03), (11.5, 1.5), (145, 4), (7.83, 1.69)),
    32: ((4.59, 0.11), (2.67, 0.11), (10.1, 1.1), (133, 4), (8.85, 7.09)),
    64: ((3.59, 0.17), (1.53, 0.05), (7.59, 1.33), (63.1, 3.3), (2.95, 1.04)),
    128: ((2.74, 0.07), (1.13, 0.03), (6.80, 1.20), (41.3, 6.9), (2.90, 0.60)),
    190: ((2.61, 0.08), (1.08, 0.03), (7.09, 1.97), (34.5, 13.2), (1.54, 0.25)),
}
PAPER_COLS = ('max_position_m', 'resting_position_m', 'time_until_resting_s', 'max_power_w', 'avg_resting_power_mw')
PAPER_HEAD = ('Max Pos. [m]', 'Resting Pos. [m]', 'Time until Resting [s]', 'Max Power [W]', 'Avg. Resting Power [mW]')
PHYS_COLS = ('max_displacement_m', 'resting_displacement_m', 'settle_time_s', 'peak_mechanical_power_w',
             'mean_resting_mechanical_power_w')
PHYS_HEAD = ('max |Δx| [m]', 'rest Δx [m]', 'settle 8 cm [s]', 'peak mech. power, 2 wheels [W]',
             'mean resting mech. power [W]')
BETA_ROWS = (16, 32, 64, 128, 190)


def _table2_args(p):
    p.add_argument('--out', default='out/table2', help='output folder (report.md, PNGs, JSON, learned betas)')
    p.add_argument('--runs', type=int, default=7, help='stand-up-and-balance runs per beta (noise seeds 0..runs-1)')
    p.add_argument('--poses', type=int, default=189,
                   help='poses to learn from (default 189: beta_190 = row 189, the paper\'s numbering)')
    p.add_argument('--order', choices=('authors', 'file'), default='authors',
                   help="pose order: the authors' hardware training order of the filtered poses (kit "
                        "hardware_balanced_poses_train.csv) or the file order of finalSetMunzir.txt")
    p.add_argument('--seconds', type=float, default=62.0, help='length of each balancing run (s)')
    p.add_argument('--kit', default=None, help='real-data kit folder (default $KRANG_DATA or ../shared/krang_data)')
    p.add_argument('--true-beta', default=None, help='hidden truth (default config/sim_true_beta.yaml)')
    p.add_argument('--params', default=None, help='controller YAML (default config/controller.yaml)')
    p.add_argument('--seed', type=int, default=0, help='seed of the learning session')
    p.add_argument('--betas', default=None, metavar='FILE',
                   help='skip the learning: take the betas (row k = after k updates) from FILE, e.g. the '
                        'learned_betas.txt of an earlier run')
    p.add_argument('--paper-era-pd', action='store_true',
                   help="the 2018 runs' controller instead of ours: the paper-era stand PD (250, 40, 4, 10) "
                        'for the whole run (on the hardware the switch to balance needed |theta| < 0.034 rad, '
                        'which the learned betas never met), no ADRC')
    p.add_argument('--extended-model', default=None, metavar='YAML',
                   help='simulate the robot with the effects `krang discrepancy` found (its extended_model.yaml, '
                        'e.g. from the hardware Table II runs), to compare the simulated table with the hardware')
    p.add_argument('--json', action='store_true', help='print the table as JSON on the last stdout line')


#: the paper-era gains.txt stand gains (krang_data README), kept for the whole run
PAPER_ERA_PD = {'stand_gains': (250.0, 40.0, 4.0, 10.0, 0.0, 0.0), 'stand_settle_s': 1e9,
                'stand_timeout_s': 0.0}


def table2_poses(kit, n, order='authors', robot=None, seed=0):
    """(train poses (n, 16), held-out poses, description)."""
    if kit is not None:
        poses, authors, src = load_filtered_poses(kit)
        if order == 'authors' and authors is not None:
            idx = list(authors)
            desc = f"{src}, the authors' training order (hardware_balanced_poses_train.csv)"
        else:
            idx = list(range(len(poses)))
            desc = f'{src}, file order'
        if n > len(idx):
            rest = [k for k in range(len(poses)) if k not in set(idx)]
            idx += rest
        train_idx = idx[:n]
        held = np.delete(poses, sorted(set(train_idx)), axis=0)
        return poses[train_idx], held, desc
    from krang_pose_server.pool import generate_pool
    res = generate_pool(n + 200, seed=seed, robot=robot)
    return res.joints[:n], res.joints[n:], f'random balanced poses of krang_pose_server.pool (seed {seed})'


def _power_trace(run):
    """(t since motion start, the paper's instantaneous power |tau w| in W) of one run, or None."""
    from krang_adrc_controller.metrics import PAPER, centred_moving_average
    s = centred_moving_average(run.i_left, PAPER.smoothing_window)
    above = np.flatnonzero(np.abs(s) > PAPER.motion_threshold_a)
    if above.size == 0:
        return None
    st = int(above[0])
    p = np.abs(s * PAPER.gear_ratio * PAPER.torque_constant_nm_per_a * run.dx_wheel_rad_s)
    return run.t[st:] - run.t[st], p[st:]


def _run_table2(args):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from tqdm import tqdm
    from krang_adrc_controller.metrics import compute_metrics
    from krang_model.beta import save_beta
    from krang_model.com import balance_pitch
    from krang_model.com import com_error
    from krang_com_estimator.estimators import make_estimator
    from krang_sim.closed_loop import TABLE2_POSE, run_balance, run_online_session, stand_pose
    robot, true_beta, cfg = _setup(args)
    sim_config = None
    if args.extended_model:
        from krang_discrepancy.report import load_extended_model
        from krang_sim.physics import SimConfig
        sim_config = SimConfig(effects=load_extended_model(args.extended_model)[0])
    # the paper's experiment: the authors' ADRC law, without our balance-point observer (with it every beta
    # rests at its reference, and the Resting Pos column would measure nothing)
    cfg = cfg.replace(balance_point_observer=False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    kit = kit_dir(args.kit)
    train, held, pose_desc = table2_poses(kit, args.poses, args.order, robot)
    beta0 = robot.nominal_beta.copy()
    t_start = time.perf_counter()
    # --- 1. online learning in closed loop (our controller), or betas from a file
    if args.betas:
        betas = np.loadtxt(args.betas, ndmin=2)
        session = None
        point_err = []
        learn_desc = f'betas read from `{args.betas}` ({len(betas) - 1} updates; no learning in this run)'
    else:
        learner = make_estimator('paper-gd', robot, beta0)
        session = run_online_session(robot, true_beta, beta0, train, learner, seed=args.seed,
                                     controller_config=cfg, sim_config=sim_config, progress=True)
        betas = session.betas
        point_err = [p.q_base - tp for p, tp in zip(session.points, session.true_pitch)]
        learn_desc = (f'paper GD (eta 300) from beta_0 (URDF) on the simulated robot (hidden truth '
                      f'`config/sim_true_beta.yaml`), {len(session.points)} poses from {pose_desc}; the controller '
                      f'stood up in the Table II pose with the waist at {stand_pose(robot, beta0)[0]:.3f} rad (where '
                      f"beta_0 agrees to stand) and learned each pose from the detector's point "
                      f'({session.sim_s:.0f} s simulated, {session.wall_s:.0f} s wall). Detector q_base - true '
                      f'balance pitch: mean |.| {1e3 * np.mean(np.abs(point_err)):.2f} mrad, max '
                      f'{1e3 * np.max(np.abs(point_err)):.2f} mrad. Failures: {session.failures or "none"}.')
    np.savetxt(out / 'learned_betas.txt', betas, fmt='%.12g')
    curve = [com_error(robot, b, true_beta, held) for b in betas]
    bt = balance_pitch(robot, TABLE2_POSE[None], true_beta)[0]
    delta_t2 = [float(bt - balance_pitch(robot, TABLE2_POSE[None], b)[0]) for b in betas]
    run_cfg = cfg.replace(**PAPER_ERA_PD) if args.paper_era_pd else cfg
    ctl_desc = ('the paper-era stand PD (250, 40, 4, 10) for the whole run, as the 2018 runs (`--paper-era-pd`)'
                if args.paper_era_pd else "stand up with the hardware stand PD, balance with the paper's ADRC law "
                '(config/controller.yaml with balance_point_observer off)')
    # --- 2. balancing runs
    rows = [('beta_0', betas[0])]
    rows += [(f'beta_{n}', betas[n - 1]) for n in BETA_ROWS if n - 1 < len(betas)]
    rows.append(('TRUE beta', true_beta))
    results = {}
    traces = {}
    standup = {}
    bar = tqdm(total=len(rows) * args.runs, desc='balancing runs', unit='run', leave=False)
    for name, beta in rows:
        res = []
        traces[name] = []
        for seed in range(args.runs):
            run = run_balance(robot, true_beta, beta, seconds=args.seconds, seed=seed, controller_config=run_cfg,
                              sim_config=sim_config,
                              name=f'{name}_seed{seed}')
            ex = run.extra
            entry = {'seed': seed, 'stood_up': ex['stood_up'], 'final_mode': ex['final_mode'],
                     'theta_error_rad': ex['theta_error_rad'], 'expected_rest_offset_m': ex['expected_rest_offset_m'],
                     'theta_on_caster_model_rad': ex['theta_on_caster_model_rad'],
                     'first_stand_current_a': ex['first_stand_current_a'],
                     'refused': any('stand_refused' in e for _, e in ex['events'])}
            if seed == 0:
                standup[name] = (run.t, run.i_left, ex['x_true_m'], ex['q_base_true'])
            if ex['stood_up']:
                try:
                    m = compute_metrics(run, robot.wheel_radius)
                    entry['paper'] = {k: m[k] for k in PAPER_COLS}
                    entry['physical'] = {k: m['physical'][k] for k in PHYS_COLS}
                    tr = _power_trace(run)
                    if tr is not None:
                        traces[name].append(tr)
                except ValueError as err:
                    entry['error'] = str(err)
            if seed == 0:
                save_beta(out / f'{name.replace(" ", "_")}.txt', beta, robot)
            res.append(entry)
            bar.update(1)
        results[name] = res
    bar.close()
    wall = time.perf_counter() - t_start
    # --- 3. table
    table = {}
    for name, res in results.items():
        ok = [r for r in res if 'paper' in r]
        row = {'runs': len(res), 'stood_up': len(ok), 'refused': sum(r['refused'] for r in res),
               'theta_error_rad': res[0]['theta_error_rad'],
               'theta_on_caster_model_rad': res[0]['theta_on_caster_model_rad'],
               'first_stand_current_a': _mean_std([r['first_stand_current_a'] for r in res]),
               'expected_rest_offset_m': res[0]['expected_rest_offset_m']}
        for k in PAPER_COLS:
            row[k] = _mean_std([r['paper'][k] for r in ok])
        for k in PHYS_COLS:
            row['physical_' + k] = _mean_std([r['physical'][k] for r in ok])
        table[name] = row
    learned = [f'beta_{n}' for n in BETA_ROWS if f'beta_{n}' in table]
    trend = {}
    for k in PAPER_COLS:
        vals = [table[n][k][0] for n in learned]
        if None in vals or len(vals) < 2:
            trend[k] = None
            continue
        trend[k] = {'first': vals[0], 'last': vals[-1], 'improves': vals[-1] < vals[0],
                    'monotone': all(b <= a for a, b in zip(vals, vals[1:]))}
    summary = {'poses_learned': len(betas) - 1, 'pose_source': pose_desc if session else args.betas,
               'failures': session.failures if session else [], 'controller': ctl_desc,
               'com_error_m': {'beta_0': curve[0], 'final': curve[-1]},
               'detector_error_rad': {'mean_abs': float(np.mean(np.abs(point_err))) if point_err else None,
                                      'max_abs': float(np.max(np.abs(point_err))) if point_err else None},
               'table': {n: {k: (list(v) if isinstance(v, tuple) else v) for k, v in row.items()}
                         for n, row in table.items()},
               'trend_beta16_to_beta190': trend, 'session_sim_s': session.sim_s if session else None,
               'session_wall_s': session.wall_s if session else None,
               'wall_s': wall, 'runs_per_beta': args.runs}
    (out / 'table2.json').write_text(json.dumps(summary, indent=1))
    # --- 4. figures
    shown = [n for n in traces if traces[n]]
    fig, ax = plt.subplots(len(shown), 2, figsize=(12, 1.9 * len(shown) + 0.6), squeeze=False,
                           gridspec_kw={'width_ratios': [1, 2.5]})
    for r, name in enumerate(shown):
        for t, p in traces[name]:
            a = t <= 10.0
            ax[r, 0].plot(t[a], p[a], lw=0.8)
            b = (t >= 10.0) & (t <= 60.0)
            ax[r, 1].plot(t[b], p[b], lw=0.6)
        ax[r, 0].set_ylabel(f'{name}\nW', fontsize=8)
    ax[-1, 0].set_xlabel('time since motion start (s)')
    ax[-1, 1].set_xlabel('time since motion start (s)')
    ax[0, 0].set_title('sit -> stand transition (0-10 s)')
    ax[0, 1].set_title('balancing (10-60 s)')
    fig.suptitle(f"Simulated wheel power |tau w| (paper's definition), {args.runs} runs per beta", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / 'power_traces.png', dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for name, (t, i, x, q) in standup.items():
        m = t <= 12.0
        ax[0].plot(t[m], i[m], lw=1, label=name)
        ax[1].plot(t[m], x[m], lw=1)
        ax[2].plot(t[m], q[m], lw=1)
    ax[0].set_ylabel('left current (A)')
    ax[1].set_ylabel('x (m, truth)')
    ax[2].set_ylabel('true base pitch (rad)')
    ax[2].set_xlabel('t (s), enable at 1 s (seed 0)')
    ax[0].legend(fontsize=8, ncol=4)
    ax[0].set_title('stand-up per beta: ' + ctl_desc, fontsize=9)
    fig.tight_layout()
    fig.savefig(out / 'standup.png', dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
    ax[0].plot(100 * np.asarray(curve))
    ax[0].set_xlabel('GD updates (poses learned online)')
    ax[0].set_ylabel('mean |x_com| error, held-out poses (cm)')
    ax[0].set_title(f'learning curve ({len(held)} held-out poses)')
    ax[1].plot(delta_t2)
    ax[1].set_xlabel('GD updates')
    ax[1].set_ylabel('balance-pitch error, Table II pose (rad)')
    for n in BETA_ROWS:
        if n - 1 < len(betas):
            for a in ax:
                a.axvline(n - 1, color='grey', lw=0.5)
    fig.tight_layout()
    fig.savefig(out / 'learning_curve.png', dpi=110)
    plt.close(fig)
    # --- 5. report
    cmd = (f'krang experiment table2 --out {args.out} --runs {args.runs} --poses {args.poses} --order {args.order}'
           + (f' --betas {args.betas}' if args.betas else '') + (' --paper-era-pd' if args.paper_era_pd else '')
           + (f' --extended-model {args.extended_model}' if args.extended_model else ''))
    robot_desc = ('the nominal drive train' if sim_config is None else
                  f'the extended model of `{args.extended_model}` ({sim_config.effects})')
    lines = [f'# Table II in simulation', '', f'`{cmd}` ({wall / 60:.1f} min wall).', '',
             f'* Simulated robot: hidden truth `config/sim_true_beta.yaml`, {robot_desc}.',
             f'* Learning: {learn_desc}',
             f'* CoM error (mean |x_com|, {len(held)} held-out poses): beta_0 {100 * curve[0]:.2f} cm -> '
             f'final {100 * curve[-1]:.2f} cm.',
             '* "beta N" = the beta after N-1 updates (row N-1), the numbering of the paper\'s hardware runs.',
             f'* Runs: {args.runs} per beta (noise seeds 0..{args.runs - 1}), {args.seconds:.0f} s, sit on the caster, '
             f'enable at 1 s, {ctl_desc}; logged at 30 Hz like the hardware, metrics by '
             '`krang_adrc_controller.metrics`. "stood" = off the caster and upright over the last 2 s.',
             '* theta error = model CoM angle - true CoM angle at rest in the Table II pose; theta on caster = the '
             "model's CoM angle while sitting (the stand-up PD's first error); I0 = its first stand-up current.", '',
             "## Paper's definitions (quirks kept: Max Pos is 0.27 x a current; resting power is mJ per 33 ms step)", '',
             '| beta | stood | theta error (rad) | theta on caster (rad) | I0 (A) | ' + ' | '.join(PAPER_HEAD) + ' |',
             '|---|---|---|---|---|' + '---|' * len(PAPER_HEAD)]
    for name, row in table.items():
        cells = [_fmt(*row[k]) for k in PAPER_COLS]
        stood = f"{row['stood_up']}/{row['runs']}" + (' (refused)' if row['refused'] else '')
        i0 = row['first_stand_current_a'][0]
        i0 = 'n/a' if i0 is None else f'{i0:.1f}'
        lines.append(f"| {name} | {stood} | {row['theta_error_rad']:+.3f} | {row['theta_on_caster_model_rad']:+.3f} | "
                     f'{i0} | ' + ' | '.join(cells) + ' |')
    lines += ['', 'The paper (hardware, 7 runs):', '', '| beta | ' + ' | '.join(PAPER_HEAD) + ' |',
              '|---|' + '---|' * len(PAPER_HEAD)]
    for n, vals in PAPER_TABLE2.items():
        lines.append(f'| beta_{n} | ' + ' | '.join(f'{m:g} ± {s:g}' for m, s in vals) + ' |')
    lines += ['', '## Physical definitions', '', '| beta | ' + ' | '.join(PHYS_HEAD) + ' |',
              '|---|' + '---|' * len(PHYS_HEAD)]
    for name, row in table.items():
        lines.append(f'| {name} | ' + ' | '.join(_fmt(*row['physical_' + k]) for k in PHYS_COLS) + ' |')
    lines += ['', '## Trend beta_16 -> beta_190 (paper definitions)', '']
    for k, tr in trend.items():
        if tr is None:
            lines.append(f'* {k}: n/a')
        else:
            lines.append(f"* {k}: {tr['first']:.3g} -> {tr['last']:.3g}: "
                         f"{'improves' if tr['improves'] else 'does NOT improve'}"
                         f"{', monotone' if tr['monotone'] else ', not monotone'}")
    lines += ['', '![power traces](power_traces.png)', '', '![stand-up](standup.png)', '',
              '![learning curve](learning_curve.png)', '']
    (out / 'report.md').write_text('\n'.join(lines) + '\n')
    print('\n'.join(lines))
    if args.json:
        print_json(summary)
    return 0


register_experiment('table2', "Table II in simulation: learn online, then 7 stand-up-and-balance runs per beta",
                    _table2_args, _run_table2)
