"""The learning experiment's hardware part (krang_experiments.learning, part 3).

Algorithm 1 on the authors' own 6003-pose pool and the authors' 528 filtered poses replayed on our
betas (where a difference to the paper comes from); and k-fold cross-validation
(krang_com_estimator.cross_validate_fit) on the 189 hand-balanced records of the real-data kit,
starting from the authors' beta_0 (row 0): mean and max |x_com| on the held-out records for the
authors' GD and for our MAP (with and without the plausible region), how many records our
method needs to reach the authors' final accuracy, the physical consistency of the learned beta
and how far each body's CoM moved."""

import math
from pathlib import Path

import numpy as np

import krang_com_estimator as est
from krang_model.com import balance_pitch, phi as phi_fn
from krang_model.files import save_figure
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_pose_server.erroneous_betas import authors_betas
from krang_pose_server.filtering import filter_poses

from .common import load_authors_poses, subplots


def authors_pool_check(
    robot=None, data_dir=None, n_betas=500, seed=0, x_tol=2e-3, window=10, eta=300.0
):
    """Algorithm 1 on the authors' own 6003-pose pool, and the authors' 528 filtered poses replayed
    with GD on erroneous betas of the same recipe (each set's first pose used for the 2 cm
    rule)."""
    robot = robot or load_krang()
    data_dir = Path(data_dir)
    b0 = robot.nominal_beta
    out = {}
    q6, j6 = load_authors_poses(data_dir / 'poses' / 'random6003fullbalance0.001000tolsafe.txt')
    q_bal = balance_pitch(robot, j6, b0)
    out['authors_pool_q_base_vs_ours_max_abs_rad'] = float(np.abs(q6 - q_bal).max())
    Phi6 = phi_fn(robot, q_bal, j6)
    betas6 = authors_betas(b0, n_betas, np.random.default_rng(seed + 1), first_phi=Phi6[0])
    fr6 = filter_poses(Phi6, betas6, 'paper-l1', eta=eta, x_tol=x_tol, window=window)
    out['authors_pool_6003_filtered_poses'] = int(len(fr6.selected))
    out['authors_pool_6003_converged'] = bool(fr6.converged)
    cnt, _ = est.gd_stop_count(
        Phi6[np.random.default_rng(seed + 100).permutation(len(Phi6))], betas6, eta, x_tol, window
    )
    out['authors_pool_6003_random_order_poses'] = cnt
    q528, j528 = load_authors_poses(data_dir / 'poses' / 'finalSetMunzir.txt')
    Phi528 = phi_fn(robot, balance_pitch(robot, j528, b0), j528)
    betas528 = authors_betas(b0, n_betas, np.random.default_rng(seed + 2), first_phi=Phi528[0])
    cnt528, err528 = est.gd_stop_count(Phi528, betas528, eta, x_tol, window)
    out['authors_528_replay_stop_at'] = cnt528
    out['authors_528_replay_final_max_error_m'] = float(err528[-1])
    out['authors_528_replay_max_error_last10_m'] = float(err528[-10:].max())
    return out


# ------------------------------------------------------------------ part 3: real data
def real_data(
    robot=None,
    data_dir=None,
    k_folds=10,
    seed=0,
    sigma_hand=0.008,
    sigma_imu_deg=0.1,
    mass_frac=0.1,
    com_std=0.03,
    progress=print,
):
    """Cross-validated learning on the 189 hand-balanced records (authors' beta_0 as the start)."""
    robot = robot or load_krang()
    data_dir = Path(data_dir)
    q, j, rows = load_poses(data_dir / 'hardware_balanced_poses_train.csv', KRANG_POSE_COLUMNS)
    traj = np.loadtxt(data_dir / 'betas' / 'betaVectors1initialBetahardwareAll190Vectors.txt')
    b0 = traj[0]
    P = phi_fn(robot, q, j)
    n = len(P)
    noise = est.NoiseModel(sigma_imu_rad=math.radians(sigma_imu_deg), sigma_hand_rad=sigma_hand)
    nv = noise.variance(robot, q, j, b0)
    prior = est.physical_prior_std(robot, b0, mass_frac=mass_frac, com_std=com_std)
    A, b = est.equality_constraints(robot, robot.nominal_mass)
    folds = est.fold_split(n, k_folds, seed)
    order = np.arange(n)  # the CSV is in the authors' training order

    kw = dict(noise=noise, mass_frac=mass_frac, com_std=com_std, total_mass=robot.nominal_mass)

    def fit_map(tr):
        return est.make_estimator('map', robot, b0, **kw).fit(q[tr], j[tr])[0]

    def fit_map_unbounded(tr):  # without the stated plausible region (mass spread, CoM radius)
        return est.make_estimator('map', robot, b0, mass_spread=None, com_radius=None, **kw).fit(
            q[tr], j[tr]
        )[0]

    def fit_map_rows(model):  # the linear MAP on the paper's rows (phi) or with the EIV correction
        def f(tr):
            rows_, y_, var_ = est.balanced_pose_rows(robot, q[tr], j[tr], b0, noise, model)
            return est.map_batch(b0, prior, rows_, y_, var_, A, b)[0]

        return f

    def fit_gd(tr):
        g = est.PaperGD(robot, b0)
        g.update_rows(P[np.sort(tr)])
        return g.beta

    def fit_gd_mass(tr):
        g = est.PaperGDMass(robot, b0, total_mass=robot.nominal_mass)
        g.update_rows(P[np.sort(tr)])
        return g.beta

    res = {
        'n_records': n,
        'k_folds': k_folds,
        'noise': {
            'sigma_imu_rad': noise.sigma_imu_rad,
            'sigma_hand_rad': sigma_hand,
            'x_noise_mm_median': 1e3 * float(np.median(np.sqrt(nv))),
        },
        'prior': {'mass_frac': mass_frac, 'com_std_m': com_std},
    }
    res['in_sample'] = {
        'beta0': _err(P @ b0),
        'authors_row189': _err(P @ traj[189]),
    }
    cv = {}
    preds = {}
    for name, fit in (
        ('paper-gd', fit_gd),
        ('paper-gd-mass', fit_gd_mass),
        ('map', fit_map),
        ('map-unbounded', fit_map_unbounded),
        ('map-phi-rows', fit_map_rows('phi')),
        ('map-eiv-rows', fit_map_rows('eiv')),
    ):
        pred, pitch = est.cross_validate_fit(
            lambda tr, fit=fit: (fit(tr), None), robot, q, j, k_folds, seed
        )
        preds[name] = pred
        cv[name] = _err(pred)
        cv[name]['pitch_mean_deg'] = float(np.degrees(np.abs(pitch).mean()))
        cv[name]['pitch_max_deg'] = float(np.degrees(np.abs(pitch).max()))
        worst = int(np.argmax(np.abs(pred)))
        cv[name]['worst_pose_index'] = int(rows[worst]['pose_index'])
        cv[name]['max_without_worst_cm'] = 100 * float(np.sort(np.abs(pred))[-2])
        progress(f'CV {name}: mean {cv[name]["mean_cm"]:.3f} cm, max {cv[name]["max_cm"]:.2f} cm')
    cv['beta0'] = _err(P @ b0)
    pitch0 = np.arctan2(P @ b0, est.pitch_rows(robot, q, j) @ b0)
    cv['beta0']['pitch_mean_deg'] = float(np.degrees(np.abs(pitch0).mean()))
    cv['beta0']['pitch_max_deg'] = float(np.degrees(np.abs(pitch0).max()))
    res['cross_validation'] = cv
    # learning curve in the authors' order, cross-validated: records used (prefix of each fold's
    # training records in train order) -> mean |x_com| on the held-out fold
    curve = {'paper-gd': np.zeros(n + 1), 'map': np.zeros(n + 1)}
    counts = np.zeros(n + 1)
    for f in folds:
        tr = np.setdiff1d(order, f)
        g = est.PaperGD(robot, b0)
        m = est.MAPOnline(robot, b0, prior, noise, A, b)
        curve['paper-gd'][0] += np.abs(P[f] @ g.beta).sum()
        curve['map'][0] += np.abs(P[f] @ m.beta).sum()
        counts[0] += len(f)
        for k, i in enumerate(tr, start=1):
            g.update_row(P[i])
            m.update(q[i], j[i])
            curve['paper-gd'][k] += np.abs(P[f] @ g.beta).sum()
            curve['map'][k] += np.abs(P[f] @ m.beta).sum()
            counts[k] += len(f)
    last = min(n - len(f) for f in folds)  # every fold has at least this many training records
    for key in curve:
        curve[key] = curve[key][: last + 1] / counts[: last + 1]
    gd_final = float(curve['paper-gd'][last])
    res['learning_curve'] = {
        'records_max': last,
        'paper_gd_final_cv_mean_cm': 100 * gd_final,
        'map_records_to_reach_gd_final': _first_index_below(curve['map'], gd_final),
        'map_records_to_reach_0.46cm': _first_index_below(curve['map'], 0.0046),
        'map_records_to_reach_0.4cm': _first_index_below(curve['map'], 0.004),
        'paper_gd_records_to_reach_0.46cm': _first_index_below(curve['paper-gd'], 0.0046),
        'map_at': {
            str(k): 100 * float(curve['map'][k]) for k in (0, 5, 10, 20, 30, 40, 60, 100, last)
        },
        'paper_gd_at': {
            str(k): 100 * float(curve['paper-gd'][k])
            for k in (0, 5, 10, 20, 30, 40, 60, 100, last)
        },
    }
    # the beta learned from all 189 records
    beta_all = fit_map(np.arange(n))
    cons = est.physical_consistency(
        robot, beta_all, mass_spread=est.MASS_SPREAD, com_radius=est.COM_RADIUS_M
    )
    res['learned'] = {
        'in_sample': _err(P @ beta_all),
        'physically_consistent': cons['ok'],
        'violations': cons['violations'],
        'at_bound': cons['at_bound'],
        'total_mass_kg': cons['total_mass'],
        'com_moved_cm': {bd['name']: round(100 * bd['com_moved_m'], 2) for bd in cons['bodies']},
        'mass_change_kg': {bd['name']: round(bd['mass_change_kg'], 3) for bd in cons['bodies']},
    }
    authors_cons = est.physical_consistency(robot, traj[189])
    res['authors_row189_violations'] = authors_cons['violations']
    res['authors_row189_com_moved_cm'] = {
        bd['name']: round(100 * bd['com_moved_m'], 2) for bd in authors_cons['bodies']
    }
    return res, {'curve': curve, 'beta': beta_all, 'preds': preds}


def _err(x):
    x = np.abs(np.asarray(x))
    return {'mean_cm': 100 * float(x.mean()), 'max_cm': 100 * float(x.max()), 'n': int(len(x))}


def _first_index_below(curve, level):
    idx = np.flatnonzero(np.asarray(curve) <= level)
    return int(idx[0]) if len(idx) else None


def plot_real(curve, path):
    fig, ax = subplots(figsize=(7, 4.5))
    for name, c in curve.items():
        ax.plot(np.arange(len(c)), 100 * c, label=name)
    ax.axhline(0.46, color='gray', ls=':', label="authors' row 189, in-sample mean (0.46 cm)")
    ax.axhline(0.4, color='k', ls='--', lw=0.8, label='paper: test mean of beta_190 (0.4 cm)')
    ax.set_xlabel("training records used (authors' order)")
    ax.set_ylabel('cross-validated mean |x_com| [cm]')
    ax.set_yscale('log')
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title('Real Krang data: 10-fold CV on the 189 hand-balanced records')
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
