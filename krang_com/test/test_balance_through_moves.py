"""Balancing through a pose move on hidden truths with real-sized CoM errors, offline: the online
session's first move (the pose server's streamed straight line) from the default stand pose, on
truths of krang_sim.truths (12-25 mm forward error) and with the start model 2.5 cm forward of the
demo's truth; and (slow) full 12-pose adaptive sessions with the start model 2.5 cm off on
generated truths.

What is bounded (docs/control.md, "Pose moves"): no runaway (no max_speed_m_s stop), a wheel
travel of at most MOVE_TRAVEL_M during the move, and either a balanced point or, where the pose's
true balance pitch passes the caster, a caster catch (BALANCE -> SIT, the robot sits where it is).
And the convergence flag the pose server pauses a move on: while the joints move, whether the
robot keeps its place; at rest, whether the balance-point estimate has settled. A paused move lets
the estimate converge at the pose reached so far, the detector takes no point while a move is
pending, and with the model 2.5 cm off the moves pause and the robot strays less from its place
than without pausing."""

import numpy as np
import pytest

from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_pose_server.sequence import PoseSequence
from krang_pose_server.streaming import PauseConfig
from krang_adrc_controller.controller import load_controller_config
from krang_adrc_controller.samples import JointMotion
from krang_sim.closed_loop import ClosedLoop, Disturbance
from krang_sim.scenarios import TABLE2_POSE, run_online_session, shifted_beta, stand_pose
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


@pytest.mark.slow
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


def test_joint_motion_is_measured_over_a_window():
    """JointMotion (the node's measured motion): encoder noise is still; a move streamed at 20 Hz
    whose joints stop 10 ms between targets is moving at every decision; a stop is seen within
    two windows."""
    motion = JointMotion()
    rng = np.random.default_rng(0)
    h = 0.002
    joints = np.zeros(16)
    seen = []
    for k in range(3000):
        t = k * h
        if 1.0 <= t < 4.0:  # 0.35 rad/s for 40 ms of every 50 ms
            joints[2] += 0.35 * h if (t % 0.05) < 0.04 else 0.0
        seen.append(motion.update(t, joints + rng.normal(0.0, 1e-4, 16)))
    seen = np.array(seen)
    t = np.arange(3000) * h
    assert not seen[t < 1.0].any()
    assert seen[(t >= 1.1) & (t < 4.0)].all()
    assert not seen[t >= 4.2].any()


def balancing_loop(robot, shift_m=0.015, **config):
    true_beta = load_beta(config_path('sim_true_beta.yaml'), robot)
    wrong = shifted_beta(robot, true_beta, TABLE2_POSE, shift_m)
    cfg = load_controller_config(overrides=config)
    loop = ClosedLoop(
        robot, true_beta, wrong, TABLE2_POSE, seed=2, log_rate_hz=0, controller_config=cfg
    )
    loop.run(0.5)
    loop.controller.set_enabled(True)
    assert loop.run(15.0, until=lambda o: o.mode == 'balance')
    return loop


def test_convergence_flag_during_a_move_is_keeping_place(robot):
    """Moving joints: the flag is whether the robot stays within place_tol_m of x_ref (the
    observer's raw estimate then carries the joints' reaction torques); at rest it returns once
    the estimate has settled."""
    loop = balancing_loop(robot)
    assert not loop.last_output.balance_converged  # just entered: not yet settled
    assert loop.run(20.0, until=lambda o: o.balance_converged)
    goal = TABLE2_POSE.copy()
    goal[2] += 0.3  # an arm joint
    loop.schedule(Disturbance(loop.sim.t, 'joints', goal))
    loop.run(0.2)
    out = loop.last_output
    assert loop.sim.joints_moving and out.balance_converged and abs(out.x - out.x_ref) < 0.8
    assert loop.run(20.0, until=lambda o: not o.balance_converged)  # stopped: the hold
    assert loop.run(20.0, until=lambda o: o.balance_converged)
    assert not loop.sim.joints_moving and loop.controller.mode.value == 'balance'
    # a tolerance the move exceeds: the flag drops while the joints move
    loop = balancing_loop(robot, **{'balance_point.place_tol_m': 0.002})
    assert loop.run(20.0, until=lambda o: o.balance_converged)
    loop.schedule(Disturbance(loop.sim.t, 'joints', goal))
    assert loop.run(3.0, until=lambda o: not o.balance_converged)
    assert loop.sim.joints_moving


def test_the_flag_is_a_python_bool_with_numpy_samples(robot):
    """The node's samples carry numpy floats (its wheel angles come from an array); a numpy bool
    flag reached std_msgs/Bool as false, and the pose server never saw the flag return."""
    loop = balancing_loop(robot)
    plain = loop.control_sample

    def numpy_sample():
        sample = plain()
        sample.wheel_left, sample.wheel_right = np.array([sample.wheel_left, sample.wheel_right])
        return sample

    loop.control_sample = numpy_sample
    assert loop.run(20.0, until=lambda o: o.balance_converged)
    assert type(loop.last_output.balance_converged) is bool


def test_a_paused_move_lets_the_estimate_converge_before_the_target(robot):
    """A move started at BALANCE entry (estimate not settled) holds its first setpoint; the
    flag returns while the goal is still far, and the move then resumes and ends."""
    loop = balancing_loop(robot)
    goal = TABLE2_POSE.copy()
    goal[2] += 0.3
    loop.start_move(goal, pause=PauseConfig(max_pause_s=20.0))
    assert loop.run(20.0, until=lambda o: o.balance_converged)
    streamer = loop.streamer
    assert streamer is not None and streamer.pauses == 1 and streamer.paused_s > 1.0
    assert np.max(np.abs(goal - loop.sim.joints)) > 0.25  # the joints waited at the start
    assert loop.run(10.0, until=lambda o: loop.streamer is None)
    assert any(e.startswith('move resume') for _, e in loop.events)
    assert loop.run(5.0, until=lambda o: np.max(np.abs(goal - loop.sim.joints)) < 1e-6)


def test_no_point_while_a_move_is_pending(robot):
    """The joints still, but the pose server's target away (a paused move): no balanced point;
    the target reached, the point comes."""
    loop = balancing_loop(robot)
    far = TABLE2_POSE.copy()
    far[2] += 0.3
    loop.goal = far  # pending, never streamed: the joints stay
    assert not loop.run(20.0, until=lambda o: o.balanced_point is not None)
    assert loop.last_output.balance_converged  # settled: only the pending move holds it
    loop.goal = None
    assert loop.run(20.0, until=lambda o: o.balanced_point is not None)


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


#: the stand-up's wheel excursion bound with the start model 2.5 cm off
#: (test_twelve_poses_with_the_model_two_and_a_half_centimetres_off): the stand PD drives the
#: robot about 1 m back before it hands over (measured 1.12, 1.13, 0.91 m on truths 7400-7402;
#: their moves 0.09-1.23 m, the first the longest)
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


def adaptive_session_off_model(robot, pool, seed, n_poses, **kw):
    """The online session (adaptive selection, map-online) on generated truth `seed`, started
    from a model 2.5 cm forward of the truth at the nominal stand pose."""
    from krang_com_estimator import make_estimator
    from krang_pose_server.selection import AdaptiveSelector

    truth = generate_truth(robot, seed).beta
    beta0 = shifted_beta(robot, truth, stand_pose(robot, robot.nominal_beta), 0.025)
    return run_online_session(
        robot,
        truth,
        beta0,
        AdaptiveSelector(robot, pool),
        make_estimator('map-online', robot, beta0),
        start_pose=stand_pose(robot, beta0),
        seed=1,
        progress=False,
        log_rate_hz=50,
        n_poses=n_poses,
        **kw,
    )


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_twelve_poses_with_the_model_two_and_a_half_centimetres_off(robot):
    """With the start model 2.5 cm forward of the truth (the real robot's size) at the
    stand pose, the online session (adaptive selection, map-online) balances through every one
    of 12 moves on generated truths: 12 points, no safe stop, no caster catch, each move's wheel
    excursion (held and moving) within the campaign's bound, and the stand-up's (with its
    settling while the first move is held) within SESSION_TRAVEL_FAR_M."""
    from krang_experiments.campaign import TRAVEL_LIMIT_M
    from krang_pose_server.pool import generate_pool

    pool = generate_pool(1000, seed=7, robot=robot).joints
    for seed in (7400, 7401, 7402):
        res = adaptive_session_off_model(robot, pool, seed, 12)
        events = [e for _, e in res.loop.events]
        moves = np.maximum(res.travel_m, res.hold_travel_m)
        print(
            f'truth {seed}: {len(res.points)} poses, stand-up {res.stand_travel_m:.2f} m, '
            f'moves {np.round(moves, 2)} m (with settling: {np.round(travel_per_pose(res), 2)})'
        )
        assert not any(e.startswith(('stop reason', 'sit reason')) for e in events), events[-5:]
        assert len(res.points) == 12 and not res.failures
        assert moves.max() < TRAVEL_LIMIT_M
        assert res.stand_travel_m <= SESSION_TRAVEL_FAR_M


def excursion_per_move(res, robot):
    """Largest |x - x_ref| (m, the controller's position error) from the start of each move until
    its balanced point."""
    log = res.loop.log
    t = np.array(log['t'])
    err = np.array(log['x_wheel_rad']) * robot.wheel_radius - np.array(log['x_ref_m'])
    starts = [res.stood_up_s] + [p.t for p in res.points[:-1]]
    return np.array([np.abs(err[(t >= a) & (t <= p.t)]).max() for a, p in zip(starts, res.points)])


#: truths not used to choose balance_point.place_tol_m / place_speed_m_s (those came from the
#: demo's truth and truth 7300 with the exact model)
PAUSE_TRUTHS = (7500, 7501)


def test_moves_pause_and_stray_less_with_the_model_two_and_a_half_centimetres_off(robot):
    """The first move with the start model 2.5 cm off. Handed over at zero (the stand-up not
    watched, ``modes.stand_tries`` 0), the estimate is not settled at BALANCE entry: the move
    pauses, and the robot strays less from its position reference than without pausing
    (measured 1.02 / 1.16 m against 1.75 / 1.86 m). Handed over at the stand-up's estimate (the
    shipped controller), it strays less than that even without pausing (0.83 / 0.82 m)."""
    poses = PoseSequence.from_csv(
        config_path('excitatory_poses.csv'), robot, KRANG_POSE_COLUMNS
    ).joints
    start = stand_pose(robot, robot.nominal_beta)
    unwatched = load_controller_config(overrides={'modes.stand_tries': 0})
    for seed in PAUSE_TRUTHS:
        truth = generate_truth(robot, seed).beta
        beta0 = shifted_beta(robot, truth, start, 0.025)
        runs = {}
        for name, pause, cfg in (
            ('paused', PauseConfig(), unwatched),
            ('free', None, unwatched),
            ('handed over', None, None),
        ):
            res = run_online_session(
                robot,
                truth,
                beta0,
                poses[:1],
                start_pose=stand_pose(robot, beta0),
                seed=1,
                progress=False,
                log_rate_hz=50,
                pause=pause,
                controller_config=cfg,
            )
            assert len(res.points) == 1 and not res.failures
            runs[name] = (excursion_per_move(res, robot)[0], res.timings[0])
        (paused, timing), (free, _), (handed, _) = runs.values()
        print(
            f'truth {seed}: paused {timing["paused_s"]:.1f} s, excursion {paused:.2f} m '
            f'against {free:.2f} m; handed over at the estimate {handed:.2f} m'
        )
        assert timing['paused_s'] > 1.0
        assert paused < free - 0.3
        assert handed < paused


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_pausing_keeps_the_first_adaptive_move_near_its_reference_with_the_model_off(robot):
    """Three adaptive moves (map-online, start model 2.5 cm off) on truths not used for the
    thresholds. Handed over at zero (the stand-up unwatched, ``modes.stand_tries`` 0), pausing
    keeps the first move nearer its position reference (measured on 7400 / 7401: excursion
    1.18 / 1.18 m against 1.73 / 1.75 m). The later moves start at the reference and are paced
    (krang_pose_server.sequence), so they travel alike either way (moves 2-3: 0.40 + 0.60 /
    0.42 + 0.60 m against 0.41 + 0.59 / 0.41 + 0.58 m). Handed over at the stand-up's estimate
    (the shipped controller, pausing) the first move strays less than unwatched without pausing
    (1.15 / 1.15 m)."""
    from krang_pose_server.pool import generate_pool

    pool = generate_pool(1000, seed=7, robot=robot).joints
    unwatched = load_controller_config(overrides={'modes.stand_tries': 0})
    for seed in (7400, 7401):
        got = {}
        for name, pause, cfg in (
            ('paused', PauseConfig(), unwatched),
            ('free', None, unwatched),
            ('handed over', PauseConfig(), None),
        ):
            res = adaptive_session_off_model(
                robot, pool, seed, 3, pause=pause, controller_config=cfg
            )
            assert len(res.points) == 3 and not res.failures
            got[name] = (excursion_per_move(res, robot), travel_per_pose(res), res)
        (exc, travel, res), (exc0, travel0, _), (handed, _, _) = got.values()
        print(
            f'truth {seed}: excursion {np.round(exc, 2)} / {np.round(exc0, 2)} m, travel '
            f'{np.round(travel, 2)} / {np.round(travel0, 2)} m (with / without pausing); '
            f'handed over at the estimate {np.round(handed, 2)} m'
        )
        assert res.timings[0]['paused_s'] > 1.0
        assert exc[0] < exc0[0] - 0.5
        assert abs(travel[1:].sum() - travel0[1:].sum()) < 0.1
        assert handed[0] < exc0[0] - 0.5
