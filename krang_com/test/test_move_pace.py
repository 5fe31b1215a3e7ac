"""The pace of a pose move (krang_pose_server.sequence): the joints' speed limits, and the balance
pitch the current beta predicts along the straight joint line, which may move at most
``MAX_BALANCE_RATE_RAD_S``. The body follows its balance pitch with a lag; on a weak drive chain a
fast sweep of it puts the wheels at their current limit (docs/mujoco.md, "The pace of a move")."""

import copy

import numpy as np
import pytest

from krang_adrc_controller.controller import load_controller_config
from krang_experiments import campaign
from krang_model.com import balance_pitch
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_pose_server.pool import PosePool
from krang_pose_server.sequence import (
    MAX_BALANCE_RATE_RAD_S,
    PATH_SEGMENTS,
    StraightLineMove,
    move_times,
    path_points,
)
from krang_sim.closed_loop import ClosedLoop
from krang_sim.plant import terms_from_strings
from krang_sim.scenarios import stand_pose
from krang_sim.truths import TruthRecipe, generate_truth


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def pool(robot):
    """Poses the pace was not developed on (the development used the campaign's pool)."""
    return PosePool(robot).generate(300, seed=5).joints


def test_the_steepest_segment_of_the_balance_pitch_sets_the_time():
    start, goal = np.zeros(2), np.array([0.4, -0.2])
    limit = np.array([1.0, 1.0])
    joint_time = 0.4 / 0.8  # the slowest joint at 0.8 of its limit
    pitch = np.array([0.0, 0.01, 0.03, 0.25, 0.26])  # 4 segments, the third 0.22 rad
    assert move_times(start, goal, limit) == pytest.approx(joint_time)
    assert move_times(start, goal, limit, 0.8, pitch, 0.1) == pytest.approx(0.22 * 4 / 0.1)
    assert move_times(start, goal, limit, 0.8, pitch, 0.0) == pytest.approx(joint_time)
    # a gentle path leaves the joints' time
    assert move_times(start, goal, limit, 0.8, pitch / 100, 0.1) == pytest.approx(joint_time)
    # per goal, (segments + 1, N) pitches
    two = move_times(
        start, np.stack([goal, goal]), limit, 0.8, np.stack([pitch, pitch / 100], 1), 0.1
    )
    np.testing.assert_allclose(two, [8.8, joint_time])


def test_a_planned_move_sweeps_the_balance_pitch_no_faster_than_the_limit(robot, pool):
    """Timed as planned and sampled 2000 times, the balance pitch of each of 100 random moves
    between pool poses moves at most 4 % faster than the limit (the plan samples 64 segments);
    where the limit sets the pace, at least 90 % of it (no move is slowed more than it needs)."""
    rng = np.random.default_rng(11)
    beta = robot.nominal_beta

    def bal(joints):
        return balance_pitch(robot, joints, beta)

    bound = []
    for _ in range(100):
        a, b = pool[rng.choice(len(pool), size=2, replace=False)]
        move = StraightLineMove.plan(a, b, robot.velocity_limit, 0.8, balance=bal)
        t = np.linspace(0.0, move.duration, 2001)
        q = bal(np.array([move.at(tt) for tt in t]))
        peak = np.abs(np.diff(q)).max() / (t[1] - t[0])
        assert peak <= 1.04 * MAX_BALANCE_RATE_RAD_S
        if move.duration > move_times(a, b, robot.velocity_limit, 0.8) + 1e-9:
            bound.append(peak)
    assert len(bound) >= 5  # the limit binds on some of these moves
    assert min(bound) >= 0.9 * MAX_BALANCE_RATE_RAD_S


def test_a_paced_move_keeps_a_weak_drive_chain_off_its_current_limit(robot, pool):
    """Gear-hard chain (torque 0.6 of the commanded, 8 N m dry and 8 N m s viscous friction per
    wheel), untold; truth 7301. The move between two pool poses whose balance pitch moves fastest
    at the joints' pace (0.32 rad/s): at that pace the body lags its balance pitch by more than
    0.1 rad (0.118) and the wheels reach the drive's current limit; paced, it lags less than
    0.07 rad (0.049) and the current stays below three quarters of the limit (25 A of 49)."""
    caster = drivetrain(robot).caster_pitch
    beta = robot.nominal_beta
    best = (0.0, 0, 0)
    for a in range(0, len(pool), 3):
        q = balance_pitch(robot, path_points(pool[a], pool).reshape(-1, pool.shape[1]), beta)
        q = q.reshape(PATH_SEGMENTS + 1, -1)
        joint_time = move_times(pool[a], pool, robot.velocity_limit, 0.8)
        rate = np.abs(np.diff(q, axis=0)).max(axis=0) * PATH_SEGMENTS / np.maximum(joint_time, 0.5)
        rate[q.min(axis=0) < caster + 0.3] = 0.0  # far from the caster all the way
        b = int(np.argmax(rate))
        if rate[b] > best[0]:
            best = (rate[b], a, b)
    assert best[0] > 0.25
    first, second = pool[best[1]], pool[best[2]]
    truth = generate_truth(robot, 7301, TruthRecipe()).beta
    limit = drivetrain(robot).current_limit
    chain = terms_from_strings(robot, campaign.CHAINS['gear-hard'])
    at_first = ClosedLoop(
        robot, truth, beta, stand_pose(robot, beta), controller_config=load_controller_config(),
        terms=chain, log_rate_hz=100.0,
    )  # fmt: skip
    at_first.run(0.5)
    at_first.controller.set_enabled(True)
    assert at_first.run(30.0, until=lambda o: o.mode == 'balance')
    at_first.run(at_first.start_move(first) + 8.0)
    t0 = at_first.plant.t
    out = {}
    for rate in (0.0, MAX_BALANCE_RATE_RAD_S):
        # both moves from the same simulated state at the first pose (a copy each)
        loop = copy.deepcopy(at_first)
        loop.run(loop.start_move(second, max_balance_rate=rate) + 6.0)
        assert loop.controller.mode.value == 'balance', loop.events[-3:]
        log = {k: np.asarray(v) for k, v in loop.log.items()}
        m = log['t'] > t0
        out[rate] = (
            np.abs(log['q_base_true'][m] - log['balance_pitch_true'][m]).max(),
            np.abs(np.concatenate([log['i_left'][m], log['i_right'][m]])).max(),
        )
    print('lag (rad), peak current (A):', out)
    lag, peak = out[0.0]
    assert lag > 0.1 and peak >= 0.99 * limit
    lag, peak = out[MAX_BALANCE_RATE_RAD_S]
    assert lag < 0.07 and peak < 0.75 * limit
