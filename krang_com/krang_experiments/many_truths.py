"""The online session on many hidden truths: fixed pose list against adaptive pose selection.

Each truth is drawn by krang_sim.truths.generate_truth (masses within 8 %, CoMs moved up to 3 cm,
total mass kept, wheels centred, forward error of the nominal model 12-25 mm). For each truth and
each selection the offline closed loop (krang_sim.closed_loop.run_online_session: the simulated
robot under the BalanceController, the pose server's streamed straight-line moves, the detector's
balanced points) learns online from the nominal model with the same estimator:
- 'fixed': the meta-learned list config/excitatory_poses.csv in its order (the paper's method);
- 'adaptive': krang_pose_server.selection.AdaptiveSelector on a pool of safe, balanced poses.
The forward CoM error after each pose is measured as `krang demo` measures it (krang_model.com.
com_error over the 2000 held-out configurations of krang_bag.session_report).
"""

import copy
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from krang_bag.session_report import held_out_configurations
from krang_adrc_controller.adrc import drive_chain_overrides
from krang_adrc_controller.controller import load_controller_config
from krang_com_estimator import make_estimator
from krang_com_estimator.estimators import MAPEstimator
from krang_model.com import PoseMoments, balance_pitch, com_error
from krang_model.config import config_path
from krang_model.drivetrain import drivetrain
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_model.files import save_figure, write_text
from krang_pose_server.pool import PosePool
from krang_pose_server.selection import AdaptiveSelector, forward_gains
from krang_sim.plant import plant_terms
from krang_sim.scenarios import run_online_session
from krang_sim.truths import TruthRecipe, generate_truth

from .common import subplots

SELECTIONS = ('fixed', 'adaptive')


@dataclass
class Params:
    truth_seeds: tuple = tuple(range(5000, 5010))
    n_poses: int = 12
    selections: tuple = SELECTIONS
    method: str = 'map-online'
    pool_size: int = 1000
    pool_seed: int = 7
    sim_seed: int = 0
    error_range_m: tuple = (0.012, 0.025)
    criterion: str = 'forward'
    progress: bool = False
    plant: str = 'reduced'  # the simulated robot's physics (krang_sim.plant)
    plant_model: str | None = None  # an extended model of `krang discrepancy` (its YAML)
    effects: tuple = ()  # 'key=value' effects of krang_model.effects on top of plant_model
    path_check: bool = True  # refuse moves whose straight joint line hits the floor or itself
    chain_known: bool = False  # the controller is told the true drive chain (adrc.*)
    controller: dict = field(default_factory=dict)  # more controller overrides (dotted names)
    extra: dict = field(default_factory=dict)


def session(robot, true_beta, selection, params, pool=None, held_out=None, pose_pool=None):
    """One online session; returns a dict with the forward-error curve (m, one value per learned
    pose and the start), the failures, the poses learned, the timings and the wheel travel of
    each move. `pose_pool`: the PosePool whose ``path_clear`` vets each adaptive move (built here
    when params.path_check and it is None)."""
    held_out = held_out_configurations(robot) if held_out is None else held_out
    terms = plant_terms(robot, params.effects, params.plant_model)
    learner = make_estimator(params.method, robot, robot.nominal_beta)
    if selection == 'fixed':
        _, poses, _ = load_poses(config_path('excitatory_poses.csv'), KRANG_POSE_COLUMNS)
        chooser = poses[: params.n_poses]
    elif selection == 'adaptive':
        if params.path_check and pose_pool is None:
            pose_pool = PosePool(robot)
        pool = (
            (pose_pool or PosePool(robot)).generate(params.pool_size, seed=params.pool_seed)
            if pool is None
            else pool
        )
        chooser = AdaptiveSelector(
            robot,
            pool.joints,
            criterion=params.criterion,
            path_check=pose_pool.path_clear if params.path_check else None,
        )
    else:
        raise ValueError(f'selection must be one of {SELECTIONS}, not {selection!r}')
    res = run_online_session(
        robot,
        true_beta,
        robot.nominal_beta,
        chooser,
        learner,
        seed=params.sim_seed,
        progress=params.progress,
        n_poses=params.n_poses,
        plant=params.plant,
        terms=terms,
        controller_config=controller_config(robot, terms, params),
    )
    curve = [com_error(robot, b, true_beta, held_out) for b in res.betas]
    return {
        'curve_m': curve,
        'learned': len(res.points),
        'failures': [list(f) for f in res.failures],
        'safe_stops': res.safe_stops,
        'travel_m': list(res.travel_m),
        'hold_travel_m': list(res.hold_travel_m),
        'stand_travel_m': res.stand_travel_m,
        'refused_paths': getattr(chooser, 'refused', 0),
        'timings': res.timings,
        'sim_s': res.sim_s,
        'wall_s': res.wall_s,
        'pitch_error_rad': [p.q_base - t for p, t in zip(res.points, res.true_pitch)],
        # the points read while moving against the true balance pitch at their joints
        'move_point_errors_rad': _move_point_errors(robot, res.loop.move_points, true_beta),
    }


def _move_point_errors(robot, points, true_beta):
    if not points:
        return []
    joints = np.array([p.joints for p in points])
    true = balance_pitch(robot, joints, true_beta)
    return [float(p.q_base - t) for p, t in zip(points, true)]


def controller_config(robot, terms, params):
    """The controller's configuration for a session: the shipped one, told the true drive chain
    when params.chain_known (as an extended model of `krang discrepancy` would tell it), with
    params.controller's overrides; None when that is the shipped one."""
    overrides = (
        dict(drive_chain_overrides(terms.drive, drivetrain(robot))) if (params.chain_known) else {}
    )
    overrides.update(params.controller)
    return load_controller_config().override(overrides) if overrides else None


def exact_pitch_error(
    robot,
    true_beta,
    pool_joints,
    n_poses,
    selection='adaptive',
    pitch_std_rad=5e-4,
    seed=0,
    held_out=None,
    move_points=0,
    move_std_rad=2e-3,
    move_bias_rad=0.0,
    **selector_options,
):
    """The forward CoM error (m) after `n_poses` poses learned from their true balance pitch plus
    N(0, pitch_std_rad) noise, without the closed loop: what the choice of poses alone allows.
    selection 'adaptive' (AdaptiveSelector on the pool, `selector_options` passed on), 'first'
    (the pool's first n_poses, a random draw) or a sequence of pool indices (``best_design``).
    `move_points` > 0 also learns that many points evenly spaced on each straight-line move
    before its pose, each at its true balance pitch plus N(0, move_std_rad) and, as a lag would
    put it, `move_bias_rad` against the direction the move changes the balance pitch: what
    points taken while moving would add."""
    held_out = held_out_configurations(robot) if held_out is None else held_out
    learner = make_estimator('map-online', robot, robot.nominal_beta)
    rng = np.random.default_rng(seed)
    pool = np.asarray(pool_joints, dtype=float)
    chooser = (
        AdaptiveSelector(robot, pool, **selector_options)
        if isinstance(selection, str) and selection == 'adaptive'
        else None
    )
    order = range(n_poses) if isinstance(selection, str) else list(selection)[:n_poses]
    current = np.zeros(pool.shape[1])
    for k in range(n_poses):
        joints = (
            chooser.choose(learner.beta, learner.covariance, current).joints
            if chooser is not None
            else pool[order[k]]
        )
        if move_points:
            ends = balance_pitch(robot, np.stack([current, joints]), true_beta)
            lag = move_bias_rad * np.sign(ends[1] - ends[0])
            for a in np.linspace(0.0, 1.0, move_points + 2)[1:-1]:
                on_the_way = current + a * (joints - current)
                q = balance_pitch(robot, on_the_way[None], true_beta)[0] - lag
                learner.update(q + rng.normal(0.0, move_std_rad), on_the_way, sigma=move_std_rad)
        q = balance_pitch(robot, joints[None], true_beta)[0] + rng.normal(0.0, pitch_std_rad)
        learner.update(q, joints, sigma=pitch_std_rad)
        current = joints
    if isinstance(selection, str) and selection == 'first':
        learner.finalize()
    return com_error(robot, learner.beta, true_beta, held_out)


@dataclass
class Design:
    """A fixed set of pool poses and the mean squared forward error (m^2) over the reference
    configurations that the learner's prior expects after learning from them."""

    index: list
    expected_ms: float


class DesignObjective:
    """The learner's own expectation of a fixed design, linearised at the nominal model: the
    linear-Gaussian core of ``map-online`` at its prior (``MAPEstimator``), each pool pose's row g
    (phi at the balance pitch the nominal model predicts) with noise variance (pitch_std z)^2, and
    the mean of r^T Sigma r over the reference rows r (the held-out configurations)."""

    def __init__(self, robot, pool_joints, pitch_std_rad=2e-4, reference_joints=None):
        beta0 = robot.nominal_beta
        learner = make_estimator('map-online', robot, beta0)
        self._prior = MAPEstimator(learner.beta0, learner.prior_std, A=learner.A, b=learner.b)
        _, self.rows, z = PoseMoments(robot, np.asarray(pool_joints, float)).balance(beta0)
        self.noise = (float(pitch_std_rad) * z) ** 2
        ref = held_out_configurations(robot) if reference_joints is None else reference_joints
        self.reference = PoseMoments(robot, np.asarray(ref, float)).balance(beta0)[1]

    @property
    def prior(self):
        return self._prior.covariance

    def value(self, cov) -> float:
        return float(np.mean(np.einsum('ij,ij->i', self.reference @ cov, self.reference)))

    def learner_after(self, index):
        """The linear-Gaussian learner after the poses `index` (its own rank-one updates)."""
        core = copy.deepcopy(self._prior)
        for i in index:
            self.learn(core, i)
        return core

    def learn(self, core, i):
        core.update_row(self.rows[i], 0.0, self.noise[i])

    def posterior(self, index):
        return self.learner_after(index).covariance

    def best_addition(self, cov, exclude):
        """The pose that lowers the objective most from `cov` (not in `exclude`)."""
        gain, _ = forward_gains(cov, self.rows, self.reference, self.noise)
        gain[list(exclude)] = -np.inf
        return int(np.argmax(gain))


def best_design(objective: DesignObjective, n_poses, sweeps=10) -> Design:
    """The fixed design of `n_poses` pool poses that the learner expects to leave the least
    forward error: greedy, then exchange sweeps (each pose in turn replaced by the best other
    while that lowers the objective; a local optimum, at least as good as the greedy one). A bound
    on what the order and the choice of poses can do, not a selection to run: it knows the number
    of poses in advance and ignores the cost of the moves."""
    index = []
    core = objective.learner_after(index)
    for _ in range(n_poses):
        i = objective.best_addition(core.covariance, index)
        index.append(i)
        objective.learn(core, i)
    best = objective.value(core.covariance)
    for _ in range(sweeps):
        changed = False
        for k in range(n_poses):
            rest = index[:k] + index[k + 1 :]
            without = objective.learner_after(rest)
            i = objective.best_addition(without.covariance, rest)
            objective.learn(without, i)
            value = objective.value(without.covariance)
            if i != index[k] and value < best:
                index[k], best, changed = i, value, True
        if not changed:
            break
    return Design(index, best)


def run(params=None):
    params = params or Params()
    robot = load_krang()
    recipe = TruthRecipe(error_range_m=tuple(params.error_range_m))
    held_out = held_out_configurations(robot)
    pose_pool = PosePool(robot)
    pool = pose_pool.generate(params.pool_size, seed=params.pool_seed)
    wall = time.perf_counter()
    truths, runs = [], {s: [] for s in params.selections}
    for seed in params.truth_seeds:
        truth = generate_truth(robot, seed, recipe)
        truths.append({'seed': seed, 'draw': truth.draw, 'forward_error_m': truth.forward_error_m})
        for sel in params.selections:
            runs[sel].append(session(robot, truth.beta, sel, params, pool, held_out, pose_pool))
    return {
        'params': params,
        'truths': truths,
        'runs': runs,
        'summary': summarise(runs, params.n_poses),
        'wall_s': time.perf_counter() - wall,
    }


def summarise(runs, n_poses):
    """Per selection: how many sessions completed every pose without leaving balance, and the
    median / worst forward error after the last pose (completed sessions' last value otherwise)."""
    out = {}
    for sel, rs in runs.items():
        final = np.array([r['curve_m'][-1] for r in rs])
        out[sel] = {
            'sessions': len(rs),
            'complete': int(sum(r['learned'] == n_poses and not r['failures'] for r in rs)),
            'median_final_m': float(np.median(final)),
            'worst_final_m': float(final.max()),
        }
    return out


def report(result, out_dir):
    """Writes out_dir/many_truths.json and many_truths.png; returns the summary text."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    params, runs = result['params'], result['runs']
    fig, ax = subplots(figsize=(9, 5.5))
    colours = {'fixed': 'C0', 'adaptive': 'C3'}
    for sel, rs in runs.items():
        for r in rs:
            c = 1000 * np.asarray(r['curve_m'])
            ax.plot(np.arange(len(c)), c, '-', color=colours.get(sel, 'k'), lw=0.6, alpha=0.35)
        full = [r['curve_m'] for r in rs if len(r['curve_m']) == params.n_poses + 1]
        if full:
            med = 1000 * np.median(np.array(full), axis=0)
            ax.plot(
                np.arange(len(med)),
                med,
                'o-',
                color=colours.get(sel, 'k'),
                lw=2,
                label=f'{sel}: median of the {len(full)} complete sessions',
            )
    ax.axhline(1.0, color='grey', lw=0.8, ls='--', label='1 mm')
    ax.set_yscale('log')
    ax.set_xlabel('balanced poses learned (online, map-online estimator)')
    ax.set_ylabel('forward CoM error (mm): mean |x_com| over 2000 held-out configurations')
    ax.set_title(
        f'{len(result["truths"])} hidden truths (thin lines: one session each); '
        'fixed meta-learned list vs adaptive selection'
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / 'many_truths.png', dpi=110)
    doc = {
        'params': asdict(params),
        'truths': result['truths'],
        'summary': result['summary'],
        'wall_s': result['wall_s'],
        'runs': {s: [{k: v for k, v in r.items()} for r in rs] for s, rs in runs.items()},
    }
    write_text(out / 'many_truths.json', json.dumps(doc, indent=1, default=float))
    lines = [
        f'{s}: {v["complete"]}/{v["sessions"]} complete, median '
        f'{1000 * v["median_final_m"]:.2f} mm, worst {1000 * v["worst_final_m"]:.2f} mm '
        f'after {params.n_poses} poses'
        for s, v in result['summary'].items()
    ]
    return '\n'.join(lines)
