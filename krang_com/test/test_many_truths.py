"""The online session on robots it was not tuned on: hidden truths drawn by krang_sim.truths
(forward CoM error of the nominal model 12-25 mm), the offline closed loop, the adaptive pose
selection and the map-online estimator, every truth from its own seed (7100 on; the defaults are
tuned on seeds 1000-1010, 5000-5009 and the demo's truth).

Must show: 12 poses complete on every one of 10 truths, no safe stop, median forward error under
1.0 mm after 12 poses and the worst under 1.5 mm (slow). The fast variant runs 2 truths for 3
poses: every pose completes without a safe stop and the error falls under 3 mm."""

import itertools

import numpy as np
import pytest

from krang_experiments.many_truths import (
    DesignObjective,
    Params,
    best_design,
    exact_pitch_error,
    run,
)
from krang_model.robot import load_krang
from krang_pose_server.pool import generate_pool
from krang_pose_server.selection import AdaptiveSelector
from krang_sim.truths import TruthRecipe, generate_truth


def _check_sessions(result, n_poses):
    for truth, r in zip(result['truths'], result['runs']['adaptive']):
        curve = ', '.join(f'{1000 * c:.2f}' for c in r['curve_m'])
        print(
            f'truth seed {truth["seed"]} ({1000 * truth["forward_error_m"]:.1f} mm): '
            f'{r["learned"]} poses, failures {r["failures"]}, curve [{curve}] mm'
        )
    complete = [r['learned'] == n_poses and not r['failures'] for r in result['runs']['adaptive']]
    final = np.array([r['curve_m'][-1] for r in result['runs']['adaptive']])
    print(
        f'complete {sum(complete)}/{len(complete)}; median {1000 * np.median(final):.2f} mm, '
        f'worst {1000 * final.max():.2f} mm'
    )
    return complete, final


def test_generated_truths_follow_the_recipe():
    robot = load_krang()
    recipe = TruthRecipe()
    for seed in (7100, 7101, 7102):
        t = generate_truth(robot, seed, recipe)
        assert 0.012 <= t.forward_error_m <= 0.025
        b, b0 = t.beta.reshape(-1, 4), robot.nominal_beta.reshape(-1, 4)
        assert b[:, 0].sum() == pytest.approx(b0[:, 0].sum(), rel=1e-12)  # total mass kept
        ratio = b[:, 0] / b0[:, 0]  # within 8 %, then one common rescale
        assert ratio.max() / ratio.min() <= 1.08 / 0.92
        assert np.all(b[robot.wheel_body_ids, 1:] == 0)  # wheels centred
        np.testing.assert_array_equal(generate_truth(robot, seed, recipe).beta, t.beta)


def test_the_learning_experiments_truths_are_the_one_recipe():
    """The learning experiment's `physical` truths are the truth recipe with its options: the Base
    takes the total mass, the gripper plates stay as they are, both wheels weigh the same and sit
    on the axle, and the nominal model is off by at least 2 cm on the held-out poses. One draw of
    the plain recipe is perturbed_beta."""
    from krang_experiments.learning import PHYSICAL_TRUTHS
    from krang_model.com import PoseMoments
    from krang_sim.truths import generate_truths, perturbed_beta, perturbed_betas

    robot = load_krang()
    moments = PoseMoments(robot, generate_pool(100, seed=1, robot=robot).joints)
    T = generate_truths(robot, 5, np.random.default_rng(0), PHYSICAL_TRUTHS, moments)
    b, b0 = T.reshape(5, -1, 4), robot.nominal_beta.reshape(-1, 4)
    assert b[:, :, 0].sum(1) == pytest.approx([b0[:, 0].sum()] * 5, rel=1e-12)
    plates = [robot.body_names.index(n) for n in PHYSICAL_TRUTHS.keep_bodies]
    np.testing.assert_allclose(b[:, plates], np.broadcast_to(b0[plates], (5, len(plates), 4)))
    left, right = robot.wheel_body_ids
    assert np.all(b[:, left, 0] == b[:, right, 0]) and np.all(b[:, [left, right], 1:] == 0)
    ratio = np.delete(b[:, :, 0] / b0[:, 0], robot.body_names.index('Base'), axis=1)
    assert ratio.min() >= 0.85 and ratio.max() <= 1.15
    balance, _ = moments.errors(np.repeat(robot.nominal_beta[None], 5, 0), T)
    assert balance.min() >= 0.02
    np.testing.assert_array_equal(
        perturbed_beta(robot, 9), perturbed_betas(robot, np.random.default_rng(9), 1)[0]
    )


def test_adaptive_choice_prefers_the_pose_that_removes_the_uncertainty():
    """The pose of the largest expected gain wins when moves cost nothing; the predicted error
    after it is what the rank-one update gives, and the same pose's gain drops as it should."""
    robot = load_krang()
    from krang_pose_server.pool import generate_pool

    pool = generate_pool(50, seed=3, robot=robot).joints
    beta = robot.nominal_beta
    # cost negligible and no caster margin: pure information
    sel = AdaptiveSelector(robot, pool, settle_s=1e6, caster_margin_rad=-np.inf)
    cov = np.diag(np.full(robot.n_beta, 1e-4))
    score, gain, move, before, after, _ = sel.scores(beta, cov, pool[0])
    assert np.all(gain > 0) and np.all(after <= before + 1e-15)
    choice = sel.choose(beta, cov, pool[0])
    assert choice.index == int(np.argmax(gain))
    from krang_com_estimator import pitch_sensitivity
    from krang_model.com import balance_pitch, phi

    q = balance_pitch(robot, pool[choice.index][None], beta)
    g = phi(robot, q, pool[choice.index][None])[0]
    r = (sel.sigma_pitch * pitch_sensitivity(robot, q, pool[choice.index][None], beta)[0]) ** 2
    k = cov @ g / (g @ cov @ g + r)
    cov2 = cov - np.outer(k, g @ cov)
    _, gain2, _, before2, _, _ = sel.scores(beta, cov2, pool[0])
    assert before2 == pytest.approx(after[choice.index], rel=1e-9)
    s = g @ cov @ g  # the same row again is worth r / (2 s + r) of its first time
    assert gain2[choice.index] == pytest.approx(gain[choice.index] * r / (2 * s + r), rel=1e-6)
    assert sel.choose(beta, cov2, pool[0]).index != choice.index  # never twice


def test_move_cost_steers_the_choice_to_near_poses():
    robot = load_krang()
    from krang_pose_server.pool import generate_pool

    pool = generate_pool(200, seed=4, robot=robot).joints
    cov = np.diag(np.full(robot.n_beta, 1e-4))
    free = AdaptiveSelector(robot, pool, settle_s=1e6).scores(robot.nominal_beta, cov, pool[0])
    paid = AdaptiveSelector(robot, pool, settle_s=0.5).scores(robot.nominal_beta, cov, pool[0])
    assert paid[2][np.argmax(paid[0])] <= free[2][np.argmax(free[0])]


def lowest_true_pitch_on_moves(robot, truth, pool, margin, n_poses=12, seed=0):
    """A kinematic session (the learner told each chosen pose's true balance pitch, 0.3 mrad
    noise) from the default stand pose: the lowest true balance pitch above the caster along
    each straight-line move, rad, and the start's. Checks that every choice keeps the predicted
    margin (or the start's, if lower) on its path."""
    from krang_com_estimator import make_estimator
    from krang_model.com import balance_pitch
    from krang_sim.scenarios import stand_pose

    rng = np.random.default_rng(seed)
    learner = make_estimator('map-online', robot, robot.nominal_beta)
    sel = AdaptiveSelector(robot, pool, caster_margin_rad=margin)
    current = stand_pose(robot, robot.nominal_beta)
    start = balance_pitch(robot, current[None], truth)[0] - sel.caster_pitch
    lowest = []
    for _ in range(n_poses):
        before, _ = sel.path_margins(learner.beta, learner.covariance, current)
        choice = sel.choose(learner.beta, learner.covariance, current)
        assert choice.margin_rad >= min(margin, before)
        goal = choice.joints
        path = current + np.linspace(0.0, 1.0, 41)[1:, None] * (goal - current)
        lowest.append((balance_pitch(robot, path, truth) - sel.caster_pitch).min())
        q = balance_pitch(robot, goal[None], truth)[0] + rng.normal(0.0, 3e-4)
        learner.update(q, goal, sigma=3e-4)
        current = goal
    return np.array(lowest), start


def test_caster_margin_on_truths_it_was_not_tuned_on():
    """The choice keeps its margin (0.1 rad plus 2 posterior std of the predicted pitch) from the
    caster along every move: on truths 7300-7303 (the margin is tuned on 0-11) no move brings the
    true balance pitch within 0.2 rad of the caster, and the first one (from a stand pose that
    some truths put only 0.03 rad above it) never lower than where it starts or 0.1 rad. Without
    the margin the same sessions come within 0.13 rad."""
    from krang_pose_server.pool import generate_pool

    robot = load_krang()
    pool = generate_pool(1000, seed=7, robot=robot).joints
    for seed in range(7300, 7304):
        truth = generate_truth(robot, seed).beta
        lowest, start = lowest_true_pitch_on_moves(robot, truth, pool, 0.1)
        print(f'truth {seed}: start {start:.3f}, lowest per move {np.round(lowest, 3)}')
        assert lowest[0] >= min(start, 0.1) and lowest[1:].min() >= 0.2
    unguarded, _ = lowest_true_pitch_on_moves(
        robot, generate_truth(robot, 7300).beta, pool, -np.inf
    )
    assert unguarded.min() < 0.15


@pytest.mark.timeout(900)
def test_few_truths_few_poses_fast():
    result = run(Params(truth_seeds=(7100, 7101), n_poses=3, selections=('adaptive',)))
    complete, final = _check_sessions(result, 3)
    assert all(complete)
    assert final.max() < 0.003


@pytest.mark.slow
@pytest.mark.timeout(5400)
def test_ten_truths_twelve_poses_under_a_millimetre():
    result = run(
        Params(truth_seeds=tuple(range(7100, 7110)), n_poses=12, selections=('adaptive',))
    )
    complete, final = _check_sessions(result, 12)
    assert all(complete)
    assert np.median(final) < 1.0e-3
    assert final.max() < 1.5e-3


def test_report_draws_both_selections_and_writes_the_json(tmp_path):
    from krang_experiments.many_truths import report, summarise
    import json

    params = Params(truth_seeds=(1, 2), n_poses=2)
    runs = {
        'fixed': [
            {'curve_m': [0.015, 0.004, 0.002], 'learned': 2, 'failures': []},
            {'curve_m': [0.013], 'learned': 0, 'failures': [[0, 'left balance']]},
        ],
        'adaptive': [
            {'curve_m': [0.015, 0.003, 0.001], 'learned': 2, 'failures': []},
            {'curve_m': [0.013, 0.002, 0.0009], 'learned': 2, 'failures': []},
        ],
    }
    result = {
        'params': params,
        'truths': [{'seed': 1}, {'seed': 2}],
        'runs': runs,
        'summary': summarise(runs, 2),
        'wall_s': 1.0,
    }
    text = report(result, tmp_path)
    assert 'fixed: 1/2 complete' in text and 'adaptive: 2/2 complete' in text
    assert (tmp_path / 'many_truths.png').stat().st_size > 0
    doc = json.loads((tmp_path / 'many_truths.json').read_text())
    assert doc['summary']['adaptive']['median_final_m'] == pytest.approx(0.00095)


def test_exact_pitch_error_falls_with_the_number_of_poses():
    """What the choice of poses alone allows: with exact-ish pitches
    (0.5 mrad) on the ROS pool's first poses, 50 poses leave less error than 12, and many poses
    drive it towards zero; the adaptive choice of 12 beats the first 12 of the random pool."""
    robot = load_krang()
    pool = generate_pool(300, seed=0, robot=robot).joints
    truth = generate_truth(robot, 7200).beta
    first12, first50, first300 = (
        exact_pitch_error(robot, truth, pool, n, 'first') for n in (12, 50, 300)
    )
    adaptive12 = exact_pitch_error(robot, truth, pool, 12)
    assert first300 < first50 < first12
    assert first300 < 0.1e-3
    assert adaptive12 < first12


def test_best_design_is_the_learners_own_expectation_and_beats_greedy():
    """``best_design`` on a small pool: its posterior (the learner's rank-one updates) is the
    batch Gaussian posterior of all its rows at once, its value is no worse than the greedy
    start's, and it finds the best of all 3-pose subsets found by brute force (a local search
    that could stop short: on this pool it does not)."""
    robot = load_krang()
    pool = generate_pool(14, seed=3, robot=robot).joints
    reference = generate_pool(40, seed=4, robot=robot).joints
    obj = DesignObjective(robot, pool, reference_joints=reference)
    greedy = best_design(obj, 3, sweeps=0)
    best = best_design(obj, 3)
    assert best.expected_ms <= greedy.expected_ms

    def batch(index):
        g = obj.rows[list(index)]
        s = obj.prior
        k = s @ g.T @ np.linalg.inv(g @ s @ g.T + np.diag(obj.noise[list(index)]))
        return s - k @ g @ s

    cov = obj.posterior(best.index)
    assert np.allclose(cov, batch(best.index), rtol=0, atol=1e-9 * np.abs(obj.prior).max())
    assert obj.value(cov) == pytest.approx(best.expected_ms)
    brute = min(obj.value(batch(c)) for c in itertools.combinations(range(len(pool)), 3))
    assert best.expected_ms == pytest.approx(brute, rel=1e-6)
    assert obj.value(obj.prior) > 2 * best.expected_ms  # three poses teach the learner something


@pytest.mark.slow
def test_points_on_the_moves_add_what_twelve_poses_lack():
    """Three points on each move, unbiased at 1 mrad, lower the median error after 12 poses over
    truths 7200-7207 by a fifth or more; a lag of 3 mrad on them leaves it above the unbiased
    median (docs/learning.md). One truth can go either way: the points change the choice."""
    robot = load_krang()
    pool = generate_pool(300, seed=0, robot=robot).joints
    kw = dict(pitch_std_rad=2e-4, seed=1)
    errors = {'poses': [], 'moving': [], 'lagging': []}
    for seed in range(7200, 7208):
        truth = generate_truth(robot, seed).beta
        errors['poses'].append(exact_pitch_error(robot, truth, pool, 12, **kw))
        errors['moving'].append(
            exact_pitch_error(robot, truth, pool, 12, move_points=3, move_std_rad=1e-3, **kw)
        )
        errors['lagging'].append(
            exact_pitch_error(
                robot, truth, pool, 12, move_points=3, move_std_rad=1e-3, move_bias_rad=3e-3, **kw
            )
        )
    median = {k: float(np.median(v)) for k, v in errors.items()}
    assert median['moving'] < 0.8 * median['poses'], median
    assert median['lagging'] > median['moving'], median
