"""Learning experiments: the paper's simulation redone, learning curves, and the real hardware
data. `run(Params(...)) -> result`, `report(result, out_dir)`.

Three parts (`krang experiment learning`, docs/learning.md):
1. Algorithm 1 at the paper's scale: a pool of 20,000 safe balanced poses, 500 erroneous betas
   (authors' recipe), x_tol = 2 mm: how many filtered poses, versus GD over the pool in random
   order (paper: 528 versus > 5,000).
2. Learning curves with measurement noise (0.1 deg IMU noise on q_base): the CoM error against the
   hidden true beta at 1000 held-out random poses, for paper-GD on the filtered poses, paper-GD on
   random poses, MAP on D-optimal poses (ours) and MAP on random poses. MAP here is the batch
   Gauss-Newton MAP of the CoM-angle model on the first n poses (= MAPOnline.finalize() after n
   poses). Two settings:
   - `paper`: the paper's simulation; the truth is the nominal (URDF) beta, the estimate starts
     from an erroneous beta of the authors' recipe (held-out seed, not one of the filter's 500);
     MAP's prior is the recipe's spread around the start (masses known);
   - `physical`: the truth is drawn by the truth recipe (krang_sim.truths, PHYSICAL_TRUTHS:
     masses x U(0.85, 1.15), CoMs + U(-5, 5) cm per axis, total mass and wheel symmetry kept;
     drawn until the nominal beta is off by >= 2 cm mean), the estimate starts from the nominal
     beta; MAP uses the same physical prior as on the real data (masses 10 %, CoMs 3 cm), not the
     generating one.
   Errors, both in mm, mean over the held-out poses (krang_model.com.PoseMoments.errors):
   - `balance`: horizontal CoM error with the robot at the true balance pitch of each held-out pose
     (|x_com| of the estimate there; the ground-truth horizontal CoM error where the robot stands);
   - `position`: distance between estimated and true CoM in the sagittal plane (any pitch; this
     includes the scale of the moments, which balanced poses cannot observe: identifiability.py).
3. Real data (the real-data kit; learning_real_data.py): k-fold cross-validation on the 189
   hand-balanced training records, and Algorithm 1 on the authors' own pool.
"""

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import krang_com_estimator as est
from krang_model.com import PoseMoments, phi as phi_fn
from krang_model.robot import load_krang
from krang_model.files import save_figure, write_text
from krang_pose_server.erroneous_betas import authors_betas
from krang_pose_server.filtering import filter_poses
from krang_pose_server.pool import PosePool
from krang_sim.truths import TruthRecipe, generate_truths

from . import learning_real_data
from .common import subplots

CHECKPOINTS = (0, 1, 2, 3, 5, 7, 10, 12, 15, 20, 25, 30, 35, 40, 45, 50, 60, 70, 80, 100, 150, 200)
CHECKPOINTS += (300, 400, 500, 600, 800, 1000, 1500, 2000, 3000, 5000)


# ------------------------------------------------------------------ part 1: Algorithm 1 counts
def pool_wide_comparison(Phi, betas, filtered, random_order, eta=300.0, step=250):
    """The paper's "> 5,000 poses without meta-learning" read as a pool-wide criterion: the worst
    error max_{k, i in pool} |Phi_i^T beta_k| after GD on the filtered poses, and the number of
    random-order poses GD needs to reach the same worst error (checked every `step` poses)."""
    B = np.array(betas, dtype=float)
    for i in filtered:
        est.gd_step(B, Phi[i], eta)
    target = float(np.abs(Phi @ B.T).max())
    mean_f = float(np.abs(Phi @ B.T).mean())
    B = np.array(betas, dtype=float)
    reached = None
    curve = {}
    for n, i in enumerate(random_order, start=1):
        est.gd_step(B, Phi[i], eta)
        if n % step == 0 or n == len(random_order):
            E = np.abs(Phi @ B.T)
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
def simulate_learning(
    robot,
    pool_moments,
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

    pool_moments: the pool poses' krang_model.com.PoseMoments; heldout: the held-out poses'.
    sequences: (K, N) pool indices. learner: 'gd' (paper), 'gd-mass' or 'map' (the batch
    Gauss-Newton MAP of the CoM-angle model on the first n poses, = MAPOnline.finalize();
    warm-started from the previous checkpoint). Returns ({checkpoint: (balance (K,), position
    (K,))}, final betas)."""
    T = np.asarray(truths, dtype=float)
    B = np.array(starts, dtype=float)
    K = len(B)
    seq = np.asarray(sequences)
    N = seq.shape[1]
    out = {}
    cps = sorted(c for c in checkpoints if c <= N)
    # measured pitches: true balance pitch of each run's truth + IMU noise
    Yk, Zk, q_true = pool_moments.sequence_rows(seq, T)  # (K, N, n), (K, N)
    q_meas = q_true + sigma_q * rng.standard_normal(q_true.shape)
    P, Psi = pool_moments.phi_psi(Yk, Zk, q_meas)  # (K, N, n)
    if learner == 'map':
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
        w = est.mass_weights(B)
        B = est.project_total_mass(B, w, total_mass)
    ci = 0
    if cps and cps[0] == 0:
        out[0] = heldout.errors(B, T)
        ci = 1
    for step in range(N):
        est.gd_step(B, P[:, step], eta)
        if learner == 'gd-mass':
            B = est.project_total_mass(B, w, total_mass)
        if ci < len(cps) and step + 1 == cps[ci]:
            out[cps[ci]] = heldout.errors(B, T)
            ci += 1
    return out, B


#: the `physical` setting's truths: the truth recipe with the Base taking the total mass, the
#: gripper plates as they are and both wheels of one mass; the nominal beta >= 2 cm off on average
PHYSICAL_TRUTHS = TruthRecipe(
    mass_fraction=0.15,
    com_shift_m=0.05,
    error_range_m=(0.02, math.inf),
    total_mass_on='Base',
    keep_bodies=('lgPlate1', 'lgPlate2', 'rgPlate1', 'rgPlate2'),
    equal_wheels=True,
)


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
        cnt, _ = est.gd_stop_count(Phi[order], betas, eta, x_tol, window)
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
    heldout = PoseMoments(robot, test.joints)
    pool_moments = PoseMoments(robot, j_pool)
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
            truths = generate_truths(robot, n_runs, srng, PHYSICAL_TRUTHS, heldout)
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
                pool_moments,
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
        results['authors_pool'] = learning_real_data.authors_pool_check(
            robot, params.data_dir, seed=params.seed
        )
        progress(f"authors' pool check: {results['authors_pool']}")
        real, raw = learning_real_data.real_data(robot, params.data_dir, progress=progress)
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
        learning_real_data.plot_real(result['real_curve'], out_dir / 'real_data.png')
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
