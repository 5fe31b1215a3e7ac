"""Balancing through a pose move on hidden truths with real-sized CoM errors (issue 14, item 2),
offline: the online session's first move (the pose server's streamed straight line) from the
default stand pose, on truths of krang_sim.truths (12-25 mm forward error) and with the start
model 2.5 cm forward of the demo's truth; and (slow) full 12-pose adaptive sessions with the start
model 2.5 cm off on generated truths.

What is bounded (docs/control.md, "Pose moves"): no runaway (no max_speed_m_s stop), a wheel
travel of at most MOVE_TRAVEL_M during the move, and either a balanced point or, where the pose's
true balance pitch passes the caster, a caster catch (BALANCE -> SIT, the robot sits where it is).
And the convergence flag the pose server reads: false while the joints move, true again once the
balance-point estimate has settled."""

import numpy as np
import pytest

from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_pose_server.sequence import PoseSequence
from krang_sim.closed_loop import (
    TABLE2_POSE,
    ClosedLoop,
    Disturbance,
    run_online_session,
    shifted_beta,
    stand_pose,
)
from krang_sim.truths import generate_truth

#: wheel travel bound during one move, m: measured 0.39-0.67 m on the generated truths
MOVE_TRAVEL_M = 0.8
#: ... with the start model 2.5 cm off the truth (measured 1.18 m)
MOVE_TRAVEL_FAR_M = 1.4
SEEDS = range(6)


@pytest.fixture(scope='module')
def robot():
    return load_krang()


def first_move(robot, truth, beta0):
    poses = PoseSequence.from_csv(
        config_path('excitatory_poses.csv'), robot, KRANG_POSE_COLUMNS
    ).joints
    res = run_online_session(
        robot, truth, beta0, poses[:1], seed=1, progress=False, log_rate_hz=50
    )
    log = res.loop.log
    t, x = np.array(log['t']), np.array(log['x_true_m'])
    moving = t >= res.stood_up_s
    return res, float(np.abs(x[moving] - x[moving][0]).max())


def outcome(res):
    events = [e for _, e in res.loop.events]
    assert not any(e.startswith('stop reason') for e in events), events[-5:]
    if res.points:
        return 'balanced'
    assert res.failures == [(0, 'left balance: sit')]
    assert any(e.startswith('sit reason: caster contact') for e in events)
    return 'caught on the caster'


def test_first_move_on_generated_truths_is_bounded(robot):
    outcomes = []
    for seed in SEEDS:
        truth = generate_truth(robot, seed)
        assert 0.012 <= truth.forward_error_m <= 0.025
        res, travel = first_move(robot, truth.beta, robot.nominal_beta)
        outcomes.append(outcome(res))
        print(
            f'seed {seed} ({1000 * truth.forward_error_m:.1f} mm): {outcomes[-1]}, '
            f'travel {travel:.2f} m'
        )
        assert travel <= MOVE_TRAVEL_M
    assert outcomes.count('balanced') >= 4


def test_first_move_with_the_model_two_and_a_half_centimetres_off(robot):
    truth = load_beta(config_path('sim_demo_true_beta.yaml'), robot)
    beta0 = shifted_beta(robot, truth, stand_pose(robot, robot.nominal_beta), 0.025)
    res, travel = first_move(robot, truth, beta0)
    assert outcome(res) == 'balanced'
    print(f'2.5 cm off: travel {travel:.2f} m')
    assert travel <= MOVE_TRAVEL_FAR_M


def test_convergence_flag_drops_during_a_move_and_returns(robot):
    true_beta = load_beta(config_path('sim_true_beta.yaml'), robot)
    wrong = shifted_beta(robot, true_beta, TABLE2_POSE, 0.015)
    loop = ClosedLoop(robot, true_beta, wrong, TABLE2_POSE, seed=2, log_rate_hz=0)
    ctl = loop.controller
    loop.run(0.5)
    ctl.set_enabled(True)
    assert loop.run(15.0, until=lambda o: o.mode == 'balance')
    assert not loop.last_output.balance_converged  # just entered: not yet settled
    assert loop.run(20.0, until=lambda o: o.balance_converged)
    goal = TABLE2_POSE.copy()
    goal[2] += 0.3  # an arm joint
    loop.schedule(Disturbance(loop.sim.t, 'joints', goal))
    loop.run(0.2)
    assert loop.sim.joints_moving and not loop.last_output.balance_converged
    assert loop.run(20.0, until=lambda o: o.balance_converged)
    assert not loop.sim.joints_moving and ctl.mode.value == 'balance'


def test_standard_error_of_a_swaying_window_is_not_the_white_noise_one():
    """The balanced pose's base_pitch uncertainty (its effort field on /balanced_pose): white
    noise gives about std/sqrt(n); a slow sway, whose samples are correlated, gives more."""
    from krang_adrc_controller.detector import standard_error

    rng = np.random.default_rng(0)
    n = 100
    white = rng.normal(0.0, 1e-3, (n, 1))
    se = standard_error(white)[0]
    assert se == pytest.approx(1e-3 / np.sqrt(n), rel=0.5)
    sway = white + 2e-3 * np.sin(np.linspace(0.0, 2.0 * np.pi, n))[:, None]
    assert standard_error(sway)[0] > 3.0 * standard_error(white)[0]


#: wheel travel bound per pose (move and settle) over full 12-pose sessions with the start model
#: 2.5 cm off (test_twelve_poses_with_the_model_two_and_a_half_centimetres_off): 0.09-1.50 m
#: measured on truths 7400-7402, the most on the fifth move
SESSION_TRAVEL_FAR_M = 2.0


def travel_per_pose(res):
    """Largest wheel travel (m) from where each move starts until its balanced point."""
    log = res.loop.log
    t, x = np.array(log['t']), np.array(log['x_true_m'])
    starts = [res.stood_up_s] + [p.t for p in res.points[:-1]]
    out = []
    for t0, p in zip(starts, res.points):
        span = (t >= t0) & (t <= p.t)
        out.append(float(np.abs(x[span] - x[span][0]).max()))
    return np.array(out)


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_twelve_poses_with_the_model_two_and_a_half_centimetres_off(robot):
    """Issue 14: with the start model 2.5 cm forward of the truth (the real robot's size) at the
    stand pose, the online session (adaptive selection, map-online) balances through every one
    of 12 moves on generated truths: 12 points, no safe stop, no caster catch, and a wheel travel
    of at most SESSION_TRAVEL_FAR_M per pose."""
    from krang_com_estimator.estimators import make_estimator
    from krang_pose_server.pool import generate_pool
    from krang_pose_server.selection import AdaptiveSelector

    pool = generate_pool(1000, seed=7, robot=robot).joints
    start = stand_pose(robot, robot.nominal_beta)
    for seed in (7400, 7401, 7402):
        truth = generate_truth(robot, seed).beta
        beta0 = shifted_beta(robot, truth, start, 0.025)
        res = run_online_session(
            robot,
            truth,
            beta0,
            AdaptiveSelector(robot, pool),
            make_estimator('map-online', robot, beta0),
            start_pose=stand_pose(robot, beta0),
            seed=1,
            progress=False,
            log_rate_hz=50,
            n_poses=12,
        )
        events = [e for _, e in res.loop.events]
        travel = travel_per_pose(res)
        print(f'truth {seed}: {len(res.points)} poses, travel per pose {np.round(travel, 2)} m')
        assert not any(e.startswith(('stop reason', 'sit reason')) for e in events), events[-5:]
        assert len(res.points) == 12 and not res.failures
        assert travel.max() <= SESSION_TRAVEL_FAR_M
