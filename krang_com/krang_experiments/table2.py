"""Table II in closed-loop simulation: online learning (the paper's GD) on the simulated robot over
the kit's filtered poses, then stand-up-and-balance runs per learned beta in the Table II pose,
plus beta_0 and the TRUE beta: the paper's and the physical metrics, power traces, the learning
curve (README, "Simulated Table II"; docs/control.md). `krang experiment table2`."""

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from krang_adrc_controller.metrics import PAPER, centred_moving_average, compute_metrics
from krang_com_estimator import make_estimator
from krang_discrepancy.extended_model import load_extended_model
from krang_model.beta import save_beta
from krang_model.com import balance_pitch, com_error
from krang_model.files import atomic_open, save_figure, write_text
from krang_pose_server.pool import generate_pool
from krang_sim.scenarios import TABLE2_POSE, run_balance, run_online_session, stand_pose

from .common import fmt, kit_dir, load_filtered_poses, mean_std, setup, subplots

PAPER_TABLE2 = {  # the paper's Table II (mean, std)
    16: ((4.70, 0.16), (2.49, 0.03), (11.5, 1.5), (145, 4), (7.83, 1.69)),
    32: ((4.59, 0.11), (2.67, 0.11), (10.1, 1.1), (133, 4), (8.85, 7.09)),
    64: ((3.59, 0.17), (1.53, 0.05), (7.59, 1.33), (63.1, 3.3), (2.95, 1.04)),
    128: ((2.74, 0.07), (1.13, 0.03), (6.80, 1.20), (41.3, 6.9), (2.90, 0.60)),
    190: ((2.61, 0.08), (1.08, 0.03), (7.09, 1.97), (34.5, 13.2), (1.54, 0.25)),
}
PAPER_COLS = (
    'max_position_m',
    'resting_position_m',
    'time_until_resting_s',
    'max_power_w',
    'avg_resting_power_mw',
)
PAPER_HEAD = (
    'Max Pos. [m]',
    'Resting Pos. [m]',
    'Time until Resting [s]',
    'Max Power [W]',
    'Avg. Resting Power [mW]',
)
PHYS_COLS = (
    'max_displacement_m',
    'resting_displacement_m',
    'settle_time_s',
    'peak_mechanical_power_w',
    'mean_resting_mechanical_power_w',
)
PHYS_HEAD = (
    'max |Δx| [m]',
    'rest Δx [m]',
    'settle 8 cm [s]',
    'peak mech. power, 2 wheels [W]',
    'mean resting mech. power [W]',
)
BETA_ROWS = (16, 32, 64, 128, 190)


#: the paper-era gains.txt stand gains (krang_data README), kept for the whole run
PAPER_ERA_PD = {
    'modes.stand_gains': (250.0, 40.0, 4.0, 10.0, 0.0, 0.0),
    'modes.stand_settle_s': 1e9,
    'safety.stand_timeout_s': 0.0,
}


@dataclass
class Params:
    runs: int = 7  # stand-up-and-balance runs per beta (noise seeds 0..runs-1)
    poses: int = 189  # poses to learn from (beta_190 = row 189, the paper's numbering)
    order: str = 'authors'  # 'authors' (hardware training order) or 'file'
    seconds: float = 62.0  # length of each balancing run (s)
    kit: str | None = None  # real-data kit folder (default: common.kit_dir())
    true_beta: str | None = None  # hidden truth (default config/sim_true_beta.yaml)
    params: str | None = None  # controller YAML (default config/controller.yaml)
    seed: int = 0  # seed of the learning session
    betas: str | None = None  # skip the learning: betas (row k = after k updates) from a file
    paper_era_pd: bool = False  # the 2018 runs' controller: the paper-era stand PD all along
    extended_model: str | None = None  # simulate the effects of a `krang discrepancy` model
    plant: str = 'reduced'  # the simulated robot's physics (krang_sim.plant)


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
    res = generate_pool(n + 200, seed=seed, robot=robot)
    return (
        res.joints[:n],
        res.joints[n:],
        f'random balanced poses of krang_pose_server.pool (seed {seed})',
    )


def terms_summary(terms, nominal=None):
    """The terms of a true robot that differ from the nominal model, as name=value."""
    from dataclasses import fields

    from krang_model.effects import ModelTerms, nominal_drive

    nominal = nominal or ModelTerms.nominal(nominal_drive())
    out = [
        f'{f.name}={getattr(terms.drive, f.name):.6g}'
        for f in fields(terms.drive)
        if getattr(terms.drive, f.name) != getattr(nominal.drive, f.name)
    ]
    for name in ('actuation_delay', 'imu_pitch_bias', 'inertia_add', 'com_shift'):
        if getattr(terms, name) != getattr(nominal, name):
            out.append(f'{name}={getattr(terms, name):.6g}')
    out += [f'payload {kg:g} kg on {link} at {tuple(p)}' for link, p, kg in terms.payloads]
    out += [f'encoder_offset {j}={v:.6g}' for j, v in terms.joint_offsets.items() if v]
    return ', '.join(out) or 'nominal'


def power_trace(run):
    """(t since motion start, the paper's instantaneous power |tau w| in W) of one run, or None."""
    s = centred_moving_average(run.i_left, PAPER.smoothing_window)
    above = np.flatnonzero(np.abs(s) > PAPER.motion_threshold_a)
    if above.size == 0:
        return None
    st = int(above[0])
    p = np.abs(s * PAPER.gear_ratio * PAPER.torque_constant_nm_per_a * run.dx_wheel_rad_s)
    return run.t[st:] - run.t[st], p[st:]


def run(params: Params, progress=True):
    """Learn (or read the betas), then the balancing runs; returns everything report() writes."""
    robot, true_beta, cfg = setup(params.true_beta, params.params)
    terms = load_extended_model(params.extended_model) if params.extended_model else None
    # the paper's experiment: the authors' ADRC law, without our balance-point observer (with it
    # every beta rests at its reference, and the Resting Pos column would measure nothing)
    cfg = cfg.override({'balance_point.enabled': False})
    kit = kit_dir(params.kit)
    train, held, pose_desc = table2_poses(kit, params.poses, params.order, robot)
    beta0 = robot.nominal_beta.copy()
    t_start = time.perf_counter()
    # --- 1. online learning in closed loop (our controller), or betas from a file
    if params.betas:
        betas = np.loadtxt(params.betas, ndmin=2)
        session = None
        point_err = []
        learn_desc = (
            f'betas read from `{params.betas}` ({len(betas) - 1} updates; no learning in this run)'
        )
    else:
        learner = make_estimator('paper-gd', robot, beta0)
        session = run_online_session(
            robot,
            true_beta,
            beta0,
            train,
            learner,
            seed=params.seed,
            controller_config=cfg,
            plant=params.plant,
            terms=terms,
            progress=progress,
        )
        betas = session.betas
        point_err = [p.q_base - tp for p, tp in zip(session.points, session.true_pitch)]
        learn_desc = (
            f'paper GD (eta 300) from beta_0 (URDF) on the simulated robot (hidden truth '
            f'`config/sim_true_beta.yaml`), {len(session.points)} poses from {pose_desc}; the '
            'controller '
            f'stood up in the Table II pose with the waist at {stand_pose(robot, beta0)[0]:.3f} '
            'rad (where '
            f"beta_0 agrees to stand) and learned each pose from the detector's point "
            f'({session.sim_s:.0f} s simulated, {session.wall_s:.0f} s wall). Detector q_base - '
            'true '
            f'balance pitch: mean |.| {1e3 * np.mean(np.abs(point_err)):.2f} mrad, max '
            f'{1e3 * np.max(np.abs(point_err)):.2f} mrad. Failures: {session.failures or "none"}.'
        )
    curve = [com_error(robot, b, true_beta, held) for b in betas]
    bt = balance_pitch(robot, TABLE2_POSE[None], true_beta)[0]
    delta_t2 = [float(bt - balance_pitch(robot, TABLE2_POSE[None], b)[0]) for b in betas]
    run_cfg = cfg.override(PAPER_ERA_PD) if params.paper_era_pd else cfg
    ctl_desc = (
        'the paper-era stand PD (250, 40, 4, 10) for the whole run, as the 2018 runs '
        '(`--paper-era-pd`)'
        if params.paper_era_pd
        else "stand up with the hardware stand PD, balance with the paper's ADRC law "
        '(config/controller.yaml with balance_point.enabled off)'
    )
    # --- 2. balancing runs
    rows = [('beta_0', betas[0])]
    rows += [(f'beta_{n}', betas[n - 1]) for n in BETA_ROWS if n - 1 < len(betas)]
    rows.append(('TRUE beta', true_beta))
    results = {}
    traces = {}
    standup = {}
    bar = tqdm(
        total=len(rows) * params.runs,
        desc='balancing runs',
        unit='run',
        leave=False,
        disable=not progress,
    )
    for name, beta in rows:
        res = []
        traces[name] = []
        for seed in range(params.runs):
            run = run_balance(
                robot,
                true_beta,
                beta,
                seconds=params.seconds,
                seed=seed,
                controller_config=run_cfg,
                plant=params.plant,
                terms=terms,
                name=f'{name}_seed{seed}',
            )
            ex = run.extra
            entry = {
                'seed': seed,
                'stood_up': ex['stood_up'],
                'final_mode': ex['final_mode'],
                'theta_error_rad': ex['theta_error_rad'],
                'expected_rest_offset_m': ex['expected_rest_offset_m'],
                'theta_on_caster_model_rad': ex['theta_on_caster_model_rad'],
                'first_stand_current_a': ex['first_stand_current_a'],
                'refused': any('stand_refused' in e for _, e in ex['events']),
            }
            if seed == 0:
                standup[name] = (run.t, run.i_left, ex['x_true_m'], ex['q_base_true'])
            if ex['stood_up']:
                try:
                    m = compute_metrics(run, robot.wheel_radius)
                    entry['paper'] = {k: m[k] for k in PAPER_COLS}
                    entry['physical'] = {k: m['physical'][k] for k in PHYS_COLS}
                    tr = power_trace(run)
                    if tr is not None:
                        traces[name].append(tr)
                except ValueError as err:
                    entry['error'] = str(err)
            res.append(entry)
            bar.update(1)
        results[name] = res
    bar.close()
    wall = time.perf_counter() - t_start
    # --- 3. table
    table = {}
    for name, res in results.items():
        ok = [r for r in res if 'paper' in r]
        row = {
            'runs': len(res),
            'stood_up': len(ok),
            'refused': sum(r['refused'] for r in res),
            'theta_error_rad': res[0]['theta_error_rad'],
            'theta_on_caster_model_rad': res[0]['theta_on_caster_model_rad'],
            'first_stand_current_a': mean_std([r['first_stand_current_a'] for r in res]),
            'expected_rest_offset_m': res[0]['expected_rest_offset_m'],
        }
        for k in PAPER_COLS:
            row[k] = mean_std([r['paper'][k] for r in ok])
        for k in PHYS_COLS:
            row['physical_' + k] = mean_std([r['physical'][k] for r in ok])
        table[name] = row
    learned = [f'beta_{n}' for n in BETA_ROWS if f'beta_{n}' in table]
    trend = {}
    for k in PAPER_COLS:
        vals = [table[n][k][0] for n in learned]
        if None in vals or len(vals) < 2:
            trend[k] = None
            continue
        trend[k] = {
            'first': vals[0],
            'last': vals[-1],
            'improves': vals[-1] < vals[0],
            'monotone': all(b <= a for a, b in zip(vals, vals[1:])),
        }
    summary = {
        'poses_learned': len(betas) - 1,
        'pose_source': pose_desc if session else params.betas,
        'failures': session.failures if session else [],
        'controller': ctl_desc,
        'com_error_m': {'beta_0': curve[0], 'final': curve[-1]},
        'detector_error_rad': {
            'mean_abs': float(np.mean(np.abs(point_err))) if point_err else None,
            'max_abs': float(np.max(np.abs(point_err))) if point_err else None,
        },
        'table': {
            n: {k: (list(v) if isinstance(v, tuple) else v) for k, v in row.items()}
            for n, row in table.items()
        },
        'trend_beta16_to_beta190': trend,
        'session_sim_s': session.sim_s if session else None,
        'session_wall_s': session.wall_s if session else None,
        'wall_s': wall,
        'runs_per_beta': params.runs,
    }
    return {
        'params': params,
        'robot': robot,
        'betas': betas,
        'rows': rows,
        'curve': curve,
        'delta_t2': delta_t2,
        'n_held': len(held),
        'traces': traces,
        'standup': standup,
        'ctl_desc': ctl_desc,
        'learn_desc': learn_desc,
        'terms': terms,
        'table': table,
        'trend': trend,
        'summary': summary,
        'wall_s': wall,
    }


def report(result, out_dir):
    """Writes out_dir/learned_betas.txt, one beta file per row, table2.json, power_traces.png,
    standup.png, learning_curve.png and report.md; returns the report's text."""
    params, betas, curve = result['params'], result['betas'], result['curve']
    traces, standup, table, trend = (
        result['traces'],
        result['standup'],
        result['table'],
        result['trend'],
    )
    ctl_desc, learn_desc, terms = result['ctl_desc'], result['learn_desc'], result['terms']
    delta_t2, wall, n_held = result['delta_t2'], result['wall_s'], result['n_held']
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_open(out / 'learned_betas.txt', 'w') as f:
        np.savetxt(f, betas, fmt='%.12g')
    if params.runs:
        for name, beta in result['rows']:
            save_beta(out / f'{name.replace(" ", "_")}.txt', beta, result['robot'])
    write_text(out / 'table2.json', json.dumps(result['summary'], indent=1))
    # --- 4. figures
    shown = [n for n in traces if traces[n]]
    fig, ax = subplots(
        len(shown),
        2,
        figsize=(12, 1.9 * len(shown) + 0.6),
        squeeze=False,
        gridspec_kw={'width_ratios': [1, 2.5]},
    )
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
    fig.suptitle(
        f"Simulated wheel power |tau w| (paper's definition), {params.runs} runs per beta",
        fontsize=10,
    )
    fig.tight_layout()
    save_figure(fig, out / 'power_traces.png', dpi=110)
    fig, ax = subplots(3, 1, figsize=(10, 8), sharex=True)
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
    save_figure(fig, out / 'standup.png', dpi=110)
    fig, ax = subplots(1, 2, figsize=(11, 3.6))
    ax[0].plot(100 * np.asarray(curve))
    ax[0].set_xlabel('GD updates (poses learned online)')
    ax[0].set_ylabel('mean |x_com| error, held-out poses (cm)')
    ax[0].set_title(f'learning curve ({n_held} held-out poses)')
    ax[1].plot(delta_t2)
    ax[1].set_xlabel('GD updates')
    ax[1].set_ylabel('balance-pitch error, Table II pose (rad)')
    for n in BETA_ROWS:
        if n - 1 < len(betas):
            for a in ax:
                a.axvline(n - 1, color='grey', lw=0.5)
    fig.tight_layout()
    save_figure(fig, out / 'learning_curve.png', dpi=110)
    # --- 5. report
    cmd = (
        f'krang experiment table2 --out {out_dir} --runs {params.runs} --poses {params.poses} '
        f'--order {params.order}'
        + (f' --betas {params.betas}' if params.betas else '')
        + (' --paper-era-pd' if params.paper_era_pd else '')
        + (f' --extended-model {params.extended_model}' if params.extended_model else '')
    )
    robot_desc = (
        'the nominal drive train'
        if terms is None
        else f'the extended model of `{params.extended_model}` ({terms_summary(terms)})'
    )
    lines = [
        '# Table II in simulation',
        '',
        f'`{cmd}` ({wall / 60:.1f} min wall).',
        '',
        f'* Simulated robot: hidden truth `config/sim_true_beta.yaml`, {robot_desc}.',
        f'* Learning: {learn_desc}',
        f'* CoM error (mean |x_com|, {n_held} held-out poses): beta_0 {100 * curve[0]:.2f} cm -> '
        f'final {100 * curve[-1]:.2f} cm.',
        '* "beta N" = the beta after N-1 updates (row N-1), the numbering of the paper\'s '
        'hardware runs.',
        f'* Runs: {params.runs} per beta (noise seeds 0..{params.runs - 1}), {params.seconds:.0f} '
        's, sit on the caster, '
        f'enable at 1 s, {ctl_desc}; logged at 30 Hz like the hardware, metrics by '
        '`krang_adrc_controller.metrics`. "stood" = off the caster and upright over the last 2 s.',
        '* theta error = model CoM angle - true CoM angle at rest in the Table II pose; theta on '
        'caster = the '
        "model's CoM angle while sitting (the stand-up PD's first error); I0 = its first stand-up "
        'current.',
        '',
        "## Paper's definitions (quirks kept: Max Pos is 0.27 x a current; resting power is mJ "
        'per 33 ms step)',
        '',
        '| beta | stood | theta error (rad) | theta on caster (rad) | I0 (A) | '
        + ' | '.join(PAPER_HEAD)
        + ' |',
        '|---|---|---|---|---|' + '---|' * len(PAPER_HEAD),
    ]
    for name, row in table.items():
        cells = [fmt(*row[k]) for k in PAPER_COLS]
        stood = f'{row["stood_up"]}/{row["runs"]}' + (' (refused)' if row['refused'] else '')
        i0 = row['first_stand_current_a'][0]
        i0 = 'n/a' if i0 is None else f'{i0:.1f}'
        lines.append(
            f'| {name} | {stood} | {row["theta_error_rad"]:+.3f} | '
            f'{row["theta_on_caster_model_rad"]:+.3f} | '
            f'{i0} | ' + ' | '.join(cells) + ' |'
        )
    lines += [
        '',
        'The paper (hardware, 7 runs):',
        '',
        '| beta | ' + ' | '.join(PAPER_HEAD) + ' |',
        '|---|' + '---|' * len(PAPER_HEAD),
    ]
    for n, vals in PAPER_TABLE2.items():
        lines.append(f'| beta_{n} | ' + ' | '.join(f'{m:g} ± {s:g}' for m, s in vals) + ' |')
    lines += [
        '',
        '## Physical definitions',
        '',
        '| beta | ' + ' | '.join(PHYS_HEAD) + ' |',
        '|---|' + '---|' * len(PHYS_HEAD),
    ]
    for name, row in table.items():
        lines.append(
            f'| {name} | ' + ' | '.join(fmt(*row['physical_' + k]) for k in PHYS_COLS) + ' |'
        )
    lines += ['', '## Trend beta_16 -> beta_190 (paper definitions)', '']
    for k, tr in trend.items():
        if tr is None:
            lines.append(f'* {k}: n/a')
        else:
            lines.append(
                f'* {k}: {tr["first"]:.3g} -> {tr["last"]:.3g}: '
                f'{"improves" if tr["improves"] else "does NOT improve"}'
                f'{", monotone" if tr["monotone"] else ", not monotone"}'
            )
    lines += [
        '',
        '![power traces](power_traces.png)',
        '',
        '![stand-up](standup.png)',
        '',
        '![learning curve](learning_curve.png)',
        '',
    ]
    write_text(out / 'report.md', '\n'.join(lines) + '\n')
    return '\n'.join(lines)
