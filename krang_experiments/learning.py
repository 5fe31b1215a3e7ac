"""Learning experiments: the paper's simulation redone, learning curves, and the real hardware
data. `run(Params(...)) -> result`, `report(result, out_dir)`.

Three parts (`krang experiment learning`, docs/learning.md):
1. Algorithm 1 at the paper's scale: a pool of 20,000 safe balanced poses, 500 erroneous betas
   (authors' recipe), x_tol = 2 mm: how many filtered poses, versus GD over the pool in random
   order (paper: 528 versus > 5,000). Also Algorithm 1 on the authors' own 6003-pose pool and the
   authors' 528 filtered poses replayed on our betas, to see where a difference to the paper comes
   from.
2. Learning curves with measurement noise (0.1 deg IMU noise on q_base): the CoM error against the
   hidden true beta at 1000 held-out random poses, for paper-GD on the filtered poses, paper-GD on
   random poses, MAP on D-optimal poses (ours) and MAP on random poses. MAP here is the batch
   Gauss-Newton MAP of the CoM-angle model on the first n poses (= MAPOnline.finalize() after n
   poses; estimators.py). Two settings:
   - `paper`: the paper's simulation; the truth is the nominal (URDF) beta, the estimate starts
     from an erroneous beta of the authors' recipe (held-out seed, not one of the filter's 500);
     MAP's prior is the recipe's spread around the start (masses known);
   - `physical`: the truth is a physically plausible perturbation of the nominal beta (masses
     x U(0.85, 1.15), CoMs + U(-5, 5) cm per axis, total mass and wheel symmetry kept; drawn until
     the nominal beta is off by >= 2 cm mean), the estimate starts from the nominal beta; MAP uses
     the same physical prior as on the real data (masses 10 %, CoMs 3 cm), not the generating one.
   Errors, both in mm, mean over the held-out poses:
   - `balance`: horizontal CoM error with the robot at the true balance pitch of each held-out pose
     (|x_com| of the estimate there; the ground-truth horizontal CoM error where the robot stands);
   - `position`: distance between estimated and true CoM in the sagittal plane (any pitch; this
     includes the scale of the moments, which balanced poses cannot observe: identifiability.py).
3. Real data (krang_data): k-fold cross-validation on the 189 hand-balanced training records,
   starting from the authors' beta_0 (row 0): mean and max |x_com| on the held-out records for the
   authors' GD and for our MAP, how many records our method needs to reach the authors' final
   accuracy, the physical consistency of the learned beta and how far each body's CoM moved.
"""

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from krang_com_estimator import estimators as est
from krang_model.com import balance_pitch, base_regressor, phi as phi_fn
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_model.files import save_figure, write_text
from krang_pose_server.erroneous_betas import authors_betas
from krang_pose_server.filtering import filter_poses
from krang_pose_server.pool import PosePool

from .common import subplots

CHECKPOINTS = (
    0,
    1,
    2,
    3,
    5,
    7,
    10,
    12,
    15,
    20,
    25,
    30,
    35,
    40,
    45,
    50,
    60,
    70,
    80,
    100,
    150,
    200,
    300,
    400,
    500,
    600,
    800,
    1000,
    1500,
    2000,
    3000,
    5000,
)


# ------------------------------------------------------------------ authors' pose files
def load_authors_poses(path):
    """(q_base, joints (N, 16)) from the authors' pose files: Munzir format (24 columns: heading,
    q_base, x, y, z, wheels, waist, torso, kinect, arms) or old DART format (25 columns:
    axis-angle, x, y, z, wheels, waist, torso, kinect, arms; q_base by the rule of
    krang_data/README.md)."""
    data = np.loadtxt(path, ndmin=2)
    if data.shape[1] == 24:
        q_base = data[:, 1]
        rest = data[:, 7:]
    elif data.shape[1] == 25:
        q_base = np.array([_dart_q_base(aa) for aa in data[:, :3]])
        rest = data[:, 8:]
    else:
        raise ValueError(f'{path}: {data.shape[1]} columns, expected 24 (Munzir) or 25 (DART)')
    joints = np.column_stack([rest[:, 0:2], rest[:, 3:17]])  # drop q_kinect
    return q_base, joints


def _dart_q_base(aa):
    angle = np.linalg.norm(aa)
    if angle < 1e-15:
        R = np.eye(3)
    else:
        k = aa / angle
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    h = math.atan2(R[0, 0], -R[1, 0])
    q = math.atan2(R[0, 1] * math.cos(h) + R[1, 1] * math.sin(h), R[2, 1])
    return (q - math.pi + math.pi) % (2 * math.pi) - math.pi


# ------------------------------------------------------------------ part 1: Algorithm 1 counts
def gd_stop_count(phi_seq, betas, eta=300.0, x_tol=2e-3, window=10):
    """GD on all betas along the pose sequence `phi_seq` (rows); the number of poses after which
    the stop rule (max_k |phi^T beta_k| < x_tol for the last `window` poses) fires, or None, and
    the per-step max error."""
    B = np.array(betas, dtype=float).T
    run = 0
    max_err = np.empty(len(phi_seq))
    for n, p in enumerate(phi_seq):
        e = p @ B
        max_err[n] = np.abs(e).max()
        B -= eta * np.outer(p, e)
        run = run + 1 if max_err[n] < x_tol else 0
        if run >= window:
            return n + 1, max_err[: n + 1]
    return None, max_err


def pool_wide_comparison(Phi, betas, filtered, random_order, eta=300.0, step=250):
    """The paper's "> 5,000 poses without meta-learning" read as a pool-wide criterion: the worst
    error max_{k, i in pool} |Phi_i^T beta_k| after GD on the filtered poses, and the number of
    random-order poses GD needs to reach the same worst error (checked every `step` poses)."""
    B = np.array(betas, dtype=float).T
    for i in filtered:
        B -= eta * np.outer(Phi[i], Phi[i] @ B)
    target = float(np.abs(Phi @ B).max())
    mean_f = float(np.abs(Phi @ B).mean())
    B = np.array(betas, dtype=float).T
    reached = None
    curve = {}
    for n, i in enumerate(random_order, start=1):
        B -= eta * np.outer(Phi[i], Phi[i] @ B)
        if n % step == 0 or n == len(random_order):
            E = np.abs(Phi @ B)
            curve[n] = (float(E.max()), float(E.mean()))
            if E.max() <= target:
                reached = n
                break
    return {
        'filtered_worst_m': target,
        'filtered_mean_m': mean_f,
        'random_poses_to_match': reached,
        'random_checked_every': step,
        'random_curve_worst_mean_m': {str(k): v for k, v in curve.items()},
    }


# ------------------------------------------------------------------ part 2: simulated learning
class HeldOut:
    """Held-out poses (joints) for scoring estimates against truths.

    Not krang_model.com.com_error: that scores one beta against one truth by the paper's x_com
    (divided by the nominal mass); this scores K estimates against K truths at once (one matrix
    product per pose set, the learning curves' hot path), divides by each beta's own mass and also
    gives the sagittal position error."""

    def __init__(self, robot, joints):
        self.robot = robot
        base = base_regressor(robot, joints)  # (N, 3, n_beta), base frame
        self.Ycol = np.ascontiguousarray(base[:, 1])
        self.Zcol = np.ascontiguousarray(base[:, 2])

    def errors(self, B_est, T):
        """B_est, T: (K, n_beta). Returns (balance (K,), position (K,)) mean errors in metres."""
        Yt, Zt = self.Ycol @ T.T, self.Zcol @ T.T
        Mt = T[:, 0::4].sum(1)
        q_true = np.arctan2(Zt, Yt)
        Ye, Ze = self.Ycol @ B_est.T, self.Zcol @ B_est.T
        Me = B_est[:, 0::4].sum(1)
        balance = np.abs(np.sin(q_true) * Ye - np.cos(q_true) * Ze) / Me
        position = np.hypot(Ye / Me - Yt / Mt, Ze / Me - Zt / Mt)
        return balance.mean(0), position.mean(0)


def simulate_learning(
    robot,
    pool_base,
    sequences,
    truths,
    starts,
    learner,
    sigma_q,
    checkpoints,
    heldout,
    rng,
    eta=300.0,
    prior_std=None,
    A=None,
    b=None,
    total_mass=None,
):
    """Run one learner for K runs (truth k, start k, pose sequence k) with noisy balance pitches.

    pool_base: (Y, Z) base-frame regressor rows of the pool poses, each (n_pool, n_beta).
    sequences: (K, N) pool indices. learner: 'gd' (paper), 'gd-mass' or 'map' (the batch
    Gauss-Newton MAP of the CoM-angle model on the first n poses, = MAPOnline.finalize();
    warm-started from the previous checkpoint). Returns ({checkpoint: (balance (K,), position
    (K,))}, final betas)."""
    Ycol, Zcol = pool_base
    T = np.asarray(truths, dtype=float)
    B = np.array(starts, dtype=float)
    K, n = B.shape
    seq = np.asarray(sequences)
    N = seq.shape[1]
    M_nom = robot.nominal_mass
    out = {}
    cps = sorted(c for c in checkpoints if c <= N)
    # measured pitches: true balance pitch of each run's truth + IMU noise
    Yk, Zk = Ycol[seq], Zcol[seq]  # (K, N, n)
    q_meas = np.arctan2(np.einsum('knj,kj->kn', Zk, T), np.einsum('knj,kj->kn', Yk, T))
    q_meas = q_meas + sigma_q * rng.standard_normal(q_meas.shape)
    s, c = np.sin(q_meas)[..., None], np.cos(q_meas)[..., None]
    P = (s * Yk - c * Zk) / M_nom  # (K, N, n)
    if learner == 'map':
        Psi = (c * Yk + s * Zk) / M_nom
        noise = est.NoiseModel(sigma_imu_rad=sigma_q, sigma_x_m=1e-6)
        for k in range(K):
            ps = prior_std[k] if np.ndim(prior_std) == 2 else prior_std
            B[k], _ = (
                est.condition_on_constraints(B[k], np.diag(ps**2), A, b)
                if A is not None and len(A)
                else (B[k], None)
            )
        for cp in cps:
            if cp > 0:
                for k in range(K):
                    ps = prior_std[k] if np.ndim(prior_std) == 2 else prior_std
                    B[k], _, _ = est.map_gauss_newton_rows(
                        P[k, :cp],
                        Psi[k, :cp],
                        starts[k],
                        ps,
                        noise,
                        A,
                        b,
                        iterations=30,
                        tol=1e-7,
                        beta_start=B[k],
                        covariance=False,
                    )
            out[cp] = heldout.errors(B, T)
        return out, B
    if learner == 'gd-mass':
        a = np.zeros(n)
        a[0::4] = 1.0
        w = np.abs(B) * a
        B = B + w * ((total_mass - B @ a) / (w @ a))[:, None]
    ci = 0
    if cps and cps[0] == 0:
        out[0] = heldout.errors(B, T)
        ci = 1
    for step in range(N):
        Pk = P[:, step]
        e = np.einsum('kj,kj->k', Pk, B)
        B -= eta * e[:, None] * Pk
        if learner == 'gd-mass':
            B = B + w * ((total_mass - B @ a) / (w @ a))[:, None]
        if ci < len(cps) and step + 1 == cps[ci]:
            out[cps[ci]] = heldout.errors(B, T)
            ci += 1
    return out, B


def physical_truths(
    robot, n, rng, mass_frac=0.15, com_range=0.05, min_error=0.02, heldout=None, max_rounds=200
):
    """Physically plausible hidden betas around the nominal one: each mass x (1 + U(-f, f)), each
    CoM coordinate + U(-d, d) m (gripper plates kept), wheels on the axle and equal, total mass
    rescaled onto the Base so it stays the nominal one; kept only when the nominal beta's mean
    balance error on the held-out poses is >= min_error."""
    b0 = robot.nominal_beta
    out = []
    plates = [i for i, nm in enumerate(robot.body_names) if 'Plate' in nm]
    base_i = robot.body_names.index('Base')
    wheels = robot.wheel_body_ids
    for _ in range(max_rounds):
        k = 4 * n
        m0 = b0[0::4]
        c0 = b0.reshape(-1, 4)[:, 1:] / m0[:, None]
        m = m0 * (1 + rng.uniform(-mass_frac, mass_frac, (k, len(m0))))
        c = c0 + rng.uniform(-com_range, com_range, (k, len(m0), 3))
        m[:, plates] = m0[plates]
        c[:, plates] = c0[plates]
        m[:, wheels[1]] = m[:, wheels[0]]
        c[:, wheels] = c0[wheels]
        m[:, base_i] += robot.nominal_mass - m.sum(1)
        T = np.concatenate([m[..., None], m[..., None] * c], axis=2).reshape(k, -1)
        if heldout is not None and min_error:
            bal, _ = heldout.errors(np.repeat(b0[None], k, 0), T)
            T = T[bal >= min_error]
        out.append(T)
        if sum(len(t) for t in out) >= n:
            return np.concatenate(out)[:n]
    raise RuntimeError('could not draw enough physical truths')


def learning_curves(
    robot=None,
    n_pool=20000,
    n_betas=500,
    n_runs=50,
    n_test=1000,
    seed=0,
    sigma_deg=0.1,
    x_tol=2e-3,
    window=10,
    eta=300.0,
    n_random=5000,
    n_map=200,
    progress=print,
    pool=None,
    filter_result=None,
):
    """Part 1 and 2. Returns a JSON-friendly dict (numbers) and the raw curves for plotting."""
    robot = robot or load_krang()
    b0 = robot.nominal_beta
    res = {
        'settings': {
            'n_pool': n_pool,
            'n_betas': n_betas,
            'n_runs': n_runs,
            'n_test': n_test,
            'seed': seed,
            'sigma_deg': sigma_deg,
            'x_tol_m': x_tol,
            'window': window,
            'eta': eta,
        }
    }
    t0 = time.perf_counter()
    pp = PosePool(robot)
    if pool is None:
        pool = pp.generate(n_pool, seed=seed)
        progress(f'pool: {n_pool} poses in {pool.seconds:.1f} s ({pool.tries} tries)')
    q_pool, j_pool = pool.q_base, pool.joints
    Phi = phi_fn(robot, q_pool, j_pool)
    betas = authors_betas(b0, n_betas, np.random.default_rng(seed + 1), first_phi=Phi[0])
    # ---- part 1: Algorithm 1 and random order
    if filter_result is None:
        filter_result = filter_poses(Phi, betas, 'paper-l1', eta=eta, x_tol=x_tol, window=window)
    fr = filter_result
    progress(
        f'Algorithm 1: {len(fr.selected)} poses (converged={fr.converged}) in {fr.seconds:.1f} s'
    )
    random_counts = []
    for k in range(3):
        order = np.random.default_rng(seed + 100 + k).permutation(n_pool)
        cnt, _ = gd_stop_count(Phi[order], betas, eta, x_tol, window)
        random_counts.append(cnt)
    progress(f'random order: {random_counts} poses (None = pool exhausted)')
    pool_wide = pool_wide_comparison(
        Phi, betas, fr.selected, np.random.default_rng(seed + 100).permutation(n_pool), eta
    )
    progress(
        f'pool-wide worst error: filtered set {1e3 * pool_wide["filtered_worst_m"]:.2f} mm after '
        f'{len(fr.selected)} poses; random order reaches it after '
        f'{pool_wide["random_poses_to_match"]}'
    )
    init_err = np.abs(Phi @ betas.T)
    res['paper_filter'] = {
        'filtered_poses': int(len(fr.selected)),
        'converged': bool(fr.converged),
        'seconds': fr.seconds,
        'random_order_poses': [None if c is None else int(c) for c in random_counts],
        'initial_error_mean_m': float(init_err.mean()),
        'initial_error_first_pose_min_m': float(np.abs(Phi[0] @ betas.T).min()),
        'pool_tries': int(pool.tries),
        'pool_wide': pool_wide,
    }
    # ---- part 2: learning curves
    test = pp.generate(n_test, seed=seed + 7)
    heldout = HeldOut(robot, test.joints)
    base_pool = base_regressor(robot, j_pool)
    pool_base = (np.ascontiguousarray(base_pool[:, 1]), np.ascontiguousarray(base_pool[:, 2]))
    sigma_q = math.radians(sigma_deg)
    A, b = est.equality_constraints(robot, robot.nominal_mass)
    curves = {}
    for setting in ('paper', 'physical'):
        srng = np.random.default_rng(seed + (11 if setting == 'paper' else 13))
        if setting == 'paper':
            truths = np.repeat(b0[None], n_runs, 0)
            starts = authors_betas(b0, n_runs, srng, first_phi=Phi[0])
            prior_std = np.array([est.recipe_prior_std(s) for s in starts])
            sel_prior = est.recipe_prior_std(b0)
        else:
            truths = physical_truths(robot, n_runs, srng, heldout=heldout)
            starts = np.repeat(b0[None], n_runs, 0)
            prior_std = est.physical_prior_std(robot, b0)
            sel_prior = prior_std
        # D-optimal selection for MAP (prior covariance conditioned on the constraints)
        _, S0 = est.condition_on_constraints(b0, np.diag(sel_prior**2), A, b)
        r_pool = (sigma_q * est.pitch_sensitivity(robot, q_pool, j_pool, b0)) ** 2
        dopt = filter_poses(
            Phi,
            betas,
            'd-optimal',
            learner='map',
            prior_cov=S0,
            noise_var=r_pool,
            x_tol=0.0,
            max_poses=n_map,
        )
        seqs = {
            'paper-gd + filtered (Alg. 1)': np.repeat(fr.selected[None], n_runs, 0),
            'paper-gd + random': np.array(
                [
                    np.random.default_rng(seed + 200 + k).permutation(n_pool)[:n_random]
                    for k in range(n_runs)
                ]
            ),
            'map + d-optimal (ours)': np.repeat(dopt.selected[None], n_runs, 0),
            'map + random': np.array(
                [
                    np.random.default_rng(seed + 300 + k).permutation(n_pool)[:n_map]
                    for k in range(n_runs)
                ]
            ),
        }
        curves[setting] = {}
        for name, seq in seqs.items():
            learner = 'map' if name.startswith('map') else 'gd'
            out, _ = simulate_learning(
                robot,
                pool_base,
                seq,
                truths,
                starts,
                learner,
                sigma_q,
                CHECKPOINTS,
                heldout,
                np.random.default_rng(seed + 400),
                eta=eta,
                prior_std=prior_std,
                A=A,
                b=b,
            )
            curves[setting][name] = out
            last = max(out)
            progress(
                f'[{setting}] {name}: balance {1e3 * out[0][0].mean():.2f} -> '
                f'{1e3 * out[last][0].mean():.2f} mm '
                f'after {last} poses; position {1e3 * out[0][1].mean():.2f} -> '
                f'{1e3 * out[last][1].mean():.2f} mm'
            )
    res['curves'] = {
        s: {
            m: {
                str(n): {
                    'balance_mm_mean': 1e3 * float(v[0].mean()),
                    'balance_mm_p90': 1e3 * float(np.percentile(v[0], 90)),
                    'position_mm_mean': 1e3 * float(v[1].mean()),
                }
                for n, v in c.items()
            }
            for m, c in cs.items()
        }
        for s, cs in curves.items()
    }
    res['poses_to_1mm'] = {
        s: {m: _first_below(c, 1e-3) for m, c in cs.items()} for s, cs in curves.items()
    }
    res['seconds'] = time.perf_counter() - t0
    return res, curves


def _first_below(curve, level):
    for n in sorted(curve):
        if curve[n][0].mean() < level:
            return int(n)
    return None


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
    cnt, _ = gd_stop_count(
        Phi6[np.random.default_rng(seed + 100).permutation(len(Phi6))], betas6, eta, x_tol, window
    )
    out['authors_pool_6003_random_order_poses'] = cnt
    q528, j528 = load_authors_poses(data_dir / 'poses' / 'finalSetMunzir.txt')
    Phi528 = phi_fn(robot, balance_pitch(robot, j528, b0), j528)
    betas528 = authors_betas(b0, n_betas, np.random.default_rng(seed + 2), first_phi=Phi528[0])
    cnt528, err528 = gd_stop_count(Phi528, betas528, eta, x_tol, window)
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
    Psi = est.pitch_rows(robot, q, j)
    n = len(P)
    noise = est.NoiseModel(sigma_imu_rad=math.radians(sigma_imu_deg), sigma_hand_rad=sigma_hand)
    nv = noise.variance(robot, q, j, b0)
    prior = est.physical_prior_std(robot, b0, mass_frac=mass_frac, com_std=com_std)
    A, b = est.equality_constraints(robot, robot.nominal_mass)
    folds = np.array_split(np.random.default_rng(seed).permutation(n), k_folds)
    order = np.arange(n)  # the CSV is in the authors' training order

    kw = dict(noise=noise, mass_frac=mass_frac, com_std=com_std, total_mass=robot.nominal_mass)

    def fit_map(tr):
        return est.make_estimator('map', robot, b0, **kw).fit(q[tr], j[tr])[0]

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
        ('map-phi-rows', fit_map_rows('phi')),
        ('map-eiv-rows', fit_map_rows('eiv')),
    ):
        pred = np.empty(n)
        pitch = np.empty(n)
        for f in folds:
            tr = np.setdiff1d(np.arange(n), f)
            beta = fit(tr)
            pred[f] = P[f] @ beta
            pitch[f] = np.arctan2(pred[f], Psi[f] @ beta)
        preds[name] = pred
        cv[name] = _err(pred)
        cv[name]['pitch_mean_deg'] = float(np.degrees(np.abs(pitch).mean()))
        cv[name]['pitch_max_deg'] = float(np.degrees(np.abs(pitch).max()))
        worst = int(np.argmax(np.abs(pred)))
        cv[name]['worst_pose_index'] = int(rows[worst]['pose_index'])
        cv[name]['max_without_worst_cm'] = 100 * float(np.sort(np.abs(pred))[-2])
        progress(f'CV {name}: mean {cv[name]["mean_cm"]:.3f} cm, max {cv[name]["max_cm"]:.2f} cm')
    cv['beta0'] = _err(P @ b0)
    cv['beta0']['pitch_mean_deg'] = float(np.degrees(np.abs(np.arctan2(P @ b0, Psi @ b0)).mean()))
    cv['beta0']['pitch_max_deg'] = float(np.degrees(np.abs(np.arctan2(P @ b0, Psi @ b0)).max()))
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
    cons = est.physical_consistency(robot, beta_all)
    res['learned'] = {
        'in_sample': _err(P @ beta_all),
        'physically_consistent': cons['ok'],
        'violations': cons['violations'],
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


# ------------------------------------------------------------------ plots and the report
def plot_curves(curves, path):
    fig, axes = subplots(2, 2, figsize=(12, 8.5), sharex=True)
    titles = {
        'paper': "paper's simulation (truth = URDF beta, start = authors' erroneous beta)",
        'physical': 'physical setting (truth = plausible perturbation, start = URDF beta)',
    }
    for col, setting in enumerate(('paper', 'physical')):
        for row, (metric, label) in enumerate(
            (
                ('balance', 'horizontal CoM error at balance [mm]'),
                ('position', 'CoM position error (sagittal) [mm]'),
            )
        ):
            ax = axes[row, col]
            for name, c in curves[setting].items():
                ns = sorted(c)
                vals = np.array([1e3 * c[n][row].mean() for n in ns])
                x = np.maximum(ns, 0.7)
                ax.plot(x, vals, marker='o', ms=3, label=name)
            ax.axhline(1.0, color='k', lw=0.8, ls='--')
            ax.set_xscale('log')
            ax.set_yscale('log')
            ax.grid(True, which='both', alpha=0.3)
            ax.set_ylabel(label)
            if row == 0:
                ax.set_title(titles[setting], fontsize=9)
            if row == 1:
                ax.set_xlabel('balanced poses learned (0 plotted at 0.7)')
            ax.legend(fontsize=7)
    fig.suptitle(
        'Learning curves, 0.1 deg IMU noise on q_base, mean over runs and 1000 held-out poses'
    )
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


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


@dataclass
class Params:
    data_dir: str | None = None  # the real-data kit: the hardware part and the authors' pool check
    parts: tuple = ('filter', 'curves', 'real')
    n_pool: int = 20000
    n_betas: int = 500
    n_runs: int = 50
    n_test: int = 1000
    sigma_deg: float = 0.1
    seed: int = 0


def run(params: Params, progress=print):
    """Everything the parts ask for: {'results' (JSON-friendly), 'curves', 'real_curve'}."""
    robot = load_krang()
    results, curves, real_curve = {}, None, None
    if 'filter' in params.parts or 'curves' in params.parts:
        res, curves = learning_curves(
            robot,
            n_pool=params.n_pool,
            n_betas=params.n_betas,
            n_runs=params.n_runs,
            n_test=params.n_test,
            seed=params.seed,
            sigma_deg=params.sigma_deg,
            progress=progress,
        )
        results.update(res)
    if params.data_dir is not None and 'real' in params.parts:
        results['authors_pool'] = authors_pool_check(robot, params.data_dir, seed=params.seed)
        progress(f"authors' pool check: {results['authors_pool']}")
        real, raw = real_data(robot, params.data_dir, progress=progress)
        results['real_data'] = real
        real_curve = raw['curve']
    return {'results': results, 'curves': curves, 'real_curve': real_curve}


def report(result, out_dir):
    """Writes out_dir/learning_results.json, learning_curves.png and real_data.png (the parts
    run)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if result['curves'] is not None:
        plot_curves(result['curves'], out_dir / 'learning_curves.png')
    if result['real_curve'] is not None:
        plot_real(result['real_curve'], out_dir / 'real_data.png')
    write_text(
        out_dir / 'learning_results.json',
        json.dumps(result['results'], indent=1, default=_jsonable),
    )


def _jsonable(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))
