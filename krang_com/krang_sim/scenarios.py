"""Scenarios on the one closed loop (``krang_sim.closed_loop.ClosedLoop``), on any plant.

* ``run_balance``: sit -> stand up -> balance for T seconds; returns a ``metrics.BalancingRun``
  (currents, x_wheel_rad, dx_wheel_rad_s, theta, ...) logged at the hardware's 30 Hz, so the
  paper's Table II definitions (20-sample smoothing, mJ-per-step "power") mean what they meant.
  The Table II runs (``krang_experiments.table2``) are these runs per learned beta.
* ``run_online_session``: the online learning loop: command a pose (a fixed list, or a chooser
  such as krang_pose_server.selection.AdaptiveSelector asked with the learner's posterior), move
  there as the pose server does (a straight line streamed at 20 Hz by the pose server's own
  ``MoveStreamer``, held while the controller's balance_converged is false), keep balancing while
  the joints move, wait for the detector's point, update beta with the learner (with the point's
  standard error), push it into the controller, repeat.
  The learner is any estimator of the registry (krang_com_estimator.estimators.make_estimator;
  default the paper's GD, ``paper-gd``): ``update(q_base, joints)``, then ``beta``.
* ``shifted_beta`` (a controlled wrong CoM) and ``stand_pose`` (a pose beta_0 agrees to stand up
  in) make their inputs.

Every scenario takes the plant (``plant``: a registered name or a ``Plant``), the true robot's
``terms`` (``krang_model.effects.ModelTerms``) and the sensors' ``noise``, as ``ClosedLoop`` does.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from krang_adrc_controller.controller import ControllerConfig
from krang_adrc_controller.metrics import BalancingRun
from krang_adrc_controller.modes import MODE_CODES
from krang_com_estimator import make_estimator
from krang_model.com import balance_pitch
from krang_model.effects import ModelTerms
from krang_pose_server.stand_pose import stand_pose as pose_server_stand_pose
from krang_pose_server.streaming import PauseConfig

from .closed_loop import ClosedLoop
from .plant import Plant
from .sensors import SensorNoise

#: The upper-body pose of the paper's Table II runs (first row of balancing_runs/table2/*.csv).
TABLE2_POSE = np.array(
    [
        2.75467,
        0.0749392,
        1.00799,
        -1.113,
        -0.000251086,
        -1.59399,
        0.0370958,
        1.02202,
        -0.0209895,
        -0.854931,
        1.113,
        0.000271173,
        1.561,
        -0.0280979,
        -1.052,
        0.0210068,
    ]
)


def shifted_beta(robot, beta, joints, shift_m, q_base=None):
    """`beta` with the Base body's mass moment changed so that, in pose `joints` at pitch `q_base`
    (default: the balance pitch of `beta`), the paper's x_com = phi^T beta moves by `shift_m` (m,
    positive = the model puts the CoM forward of where `beta` has it). A controlled "wrong CoM"."""
    beta = np.array(beta, dtype=float)
    joints = np.asarray(joints, float)
    qb = balance_pitch(robot, joints[None], beta)[0] if q_base is None else float(q_base)
    i = robot.body_names.index('Base')
    # frame-0 x axis in base coordinates is (0, sin q, -cos q) (krang_model.com)
    beta[4 * i + 2] += robot.nominal_mass * shift_m * math.sin(qb)
    beta[4 * i + 3] -= robot.nominal_mass * shift_m * math.cos(qb)
    return beta


def _mode_times(events):
    """{mode: first time entered} from controller events 'a->b: why'."""
    out = {}
    for t, e in events:
        if '->' in e and ':' in e:
            target = e.split('->', 1)[1].split(':', 1)[0]
            out.setdefault(target, t)
    return out


def run_balance(
    robot,
    true_beta,
    beta_est,
    *,
    joints=TABLE2_POSE,
    seconds: float = 60.0,
    enable_at_s: float = 1.0,
    seed: int = 0,
    controller_config: ControllerConfig | None = None,
    plant: str | Plant = 'reduced',
    terms: ModelTerms | None = None,
    noise: SensorNoise | None = None,
    disturbances=(),
    log_rate_hz: float = 30.0,
    name: str = '',
) -> BalancingRun:
    """Sit on the caster, enable at `enable_at_s` (the controller then stands up when its stand
    guard allows) and balance until `seconds`. Returns a BalancingRun logged at `log_rate_hz`;
    ``extra`` holds the truth (q_base_true, x_true_m, balance_pitch_true), modes, observer outputs,
    events, detector points, 'stood_up' (off the caster and upright for the last 2 s),
    'reached_balance_mode', 'mode_times', 'true_balance_pitch', 'theta_error_rad',
    'expected_rest_offset_m', 'theta_on_caster_model_rad', 'first_stand_current_a' and timings."""
    loop = ClosedLoop(
        robot,
        true_beta,
        beta_est,
        joints,
        controller_config=controller_config,
        plant=plant,
        terms=terms,
        noise=noise,
        seed=seed,
        log_rate_hz=log_rate_hz,
    )
    loop.schedule(*disturbances)
    wall = time.perf_counter()
    loop.run(enable_at_s)
    loop.controller.set_enabled(True)
    loop.run(seconds - enable_at_s)
    wall = time.perf_counter() - wall
    run = loop.balancing_run(name=name)
    times = _mode_times(loop.events)
    ctl = loop.controller
    # stood up = off the caster and upright (within 0.1 rad of the true balance pitch) over the
    # last 2 s, under STAND_UP or BALANCE control (a controller may balance in its stand-up mode,
    # as in 2018)
    last = run.t >= run.t[-1] - 2.0
    upright = bool(
        np.all(
            np.abs(run.extra['q_base_true'][last] - run.extra['balance_pitch_true'][last]) < 0.1
        )
    )
    stood = upright and ctl.mode.value in ('stand_up', 'balance') and 'stand_up' in times
    true_pitch = loop.plant.truth().balance_pitch
    i_first = next(
        (float(i) for i, m in zip(run.i_left, run.extra['mode']) if m == MODE_CODES['stand_up']),
        math.nan,
    )
    run.extra.update(
        stood_up=stood,
        reached_balance_mode='balance' in times,
        mode_times=times,
        final_mode=ctl.mode.value,
        first_stand_current_a=i_first,
        theta_on_caster_model_rad=ctl.drive.caster_pitch + ctl.com_offset,
        true_balance_pitch=true_pitch,
        theta_error_rad=ctl.com_offset + true_pitch,
        expected_rest_offset_m=(
            ctl.expected_rest_offset() * (ctl.com_offset + true_pitch) if ctl.design else math.nan
        ),
        wall_s=wall,
        sim_s=seconds,
        control_steps=loop.control_steps,
        seed=seed,
    )
    run.extra['loop'] = loop
    return run


@dataclass
class SessionResult:
    betas: np.ndarray  # (k + 1, n_beta): beta_0 and after each update
    points: list  # BalancedPoint per learned pose
    pose_indices: list  # index into `poses` of each point
    timings: list  # per pose: dict(move_s, settle_s, total_s, ok)
    true_pitch: list  # true balance pitch of each learned pose
    stood_up_s: float
    sim_s: float
    wall_s: float
    failures: list = field(default_factory=list)
    loop: object = None
    poses: np.ndarray = None  # the commanded poses (the chooser's picks, if adaptive)
    # the wheels' largest excursion (m): per move from where its joints began to move until its
    # point; per move while it was held before its joints moved (the first move's hold is the
    # stand-up's, so 0); the stand-up, from where the robot sat until the first move's joints
    # moved (the lift-off, a caught try's roll and re-pose, the settling after the handover)
    travel_m: list = field(default_factory=list)
    hold_travel_m: list = field(default_factory=list)
    stand_travel_m: float = 0.0

    @property
    def safe_stops(self) -> int:
        """Moves that ended in SAFE_STOP."""
        return sum('safe_stop' in str(why) for _, why in self.failures)

    @property
    def beta(self):
        return self.betas[-1]


#: the CoM angle on the caster an operator stands the robot up with: the middle of the
#: controller's stand window (modes.stand_error_min_rad .. stand_error_max_rad), rad
STAND_THETA_RAD = -6.0 * math.pi / 180.0


def stand_pose(
    robot, beta_est, base=TABLE2_POSE, target_theta_rad=STAND_THETA_RAD, caster_pitch=None
):
    """`base` (the Table II pose) with the waist set so that, sitting on the caster, the CoM angle
    the ESTIMATED beta predicts is `target_theta_rad` (the middle of the stand window): a pose the
    controller agrees to stand up in, chosen as an operator would
    (``krang_pose_server.stand_pose.stand_pose``)."""
    return pose_server_stand_pose(robot, beta_est, base, target_theta_rad, caster_pitch)


def run_online_session(
    robot,
    true_beta,
    beta0,
    poses,
    learner=None,
    *,
    start_pose=None,
    seed: int = 0,
    controller_config: ControllerConfig | None = None,
    plant: str | Plant = 'reduced',
    terms: ModelTerms | None = None,
    noise: SensorNoise | None = None,
    pose_timeout_s: float = 90.0,
    stand_timeout_s: float = 30.0,
    progress: bool = True,
    log_rate_hz: float = 0.0,
    speed_fraction: float = 0.8,
    stream_rate_hz: float = 20.0,
    pause: PauseConfig | None = PauseConfig(),
    n_poses: int | None = None,
) -> SessionResult:
    """Stand up in `start_pose` (default: ``stand_pose(robot, beta0)``, the Table II pose with the
    waist set so that beta0 agrees to stand up), then for each pose (rows of joints, pose order):
    command it, balance while the joints move, wait for the detector's point,
    ``learner.update(q_base, joints)`` (after the points read on the move, when the controller's
    ``move_points`` reads them), ``controller.set_beta(learner.beta)``. `learner`: an
    estimator of the registry, by default ``make_estimator('paper-gd', robot, beta0)``. A pose
    without a point within `pose_timeout_s` is skipped (listed in failures); if the robot leaves
    BALANCE the session ends there.

    `poses` is a fixed list, or a chooser with ``choose(beta, covariance, current_joints)``
    returning an object with ``joints`` (krang_pose_server.selection.AdaptiveSelector), asked
    before each of `n_poses` moves with the learner's current posterior. Each move is the pose
    server's streamed straight line (`speed_fraction` of the joint speed limits, targets at
    `stream_rate_hz`), held while the controller's balance_converged is false as `pause` says
    (``ClosedLoop.start_move``; None = never pause)."""
    adaptive = not isinstance(poses, (np.ndarray, list, tuple))
    if adaptive:
        chooser, poses = poses, [None] * int(n_poses)
    else:
        poses = np.atleast_2d(np.asarray(poses, float))
    learner = learner if learner is not None else make_estimator('paper-gd', robot, beta0)
    if start_pose is None:
        start_pose = stand_pose(robot, learner.beta)
    loop = ClosedLoop(
        robot,
        true_beta,
        beta0,
        start_pose,
        controller_config=controller_config,
        plant=plant,
        terms=terms,
        noise=noise,
        seed=seed,
        log_rate_hz=log_rate_hz,
    )
    ctl = loop.controller
    if np.any(np.asarray(learner.beta) != np.asarray(beta0)):
        ctl.set_beta(learner.beta)
    wall = time.perf_counter()
    loop.run(0.5)
    ctl.set_enabled(True)
    x_sit = loop.last_output.x
    stand_span = [x_sit, x_sit]  # lowest, highest wheel position (m)

    def stood(o):
        stand_span[0], stand_span[1] = min(stand_span[0], o.x), max(stand_span[1], o.x)
        return o.mode == 'balance'

    ok = loop.run(stand_timeout_s, until=stood)
    if not ok:
        raise RuntimeError(
            f'online session: the robot did not stand up within {stand_timeout_s} s '
            f'(mode {ctl.mode.value}; events {loop.events[-3:]})'
        )
    stood = loop.plant.t
    betas = [np.array(learner.beta, float)]
    points, idx, timings, true_pitch, failures, chosen = [], [], [], [], [], []
    travel, hold_travel = [], []  # per move (SessionResult.travel_m, hold_travel_m)
    n_moved = 0  # the controller's points read on the moves that the learner has
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(poses), desc='online session', unit='pose', leave=False)
    try:
        for i, pose in enumerate(poses):
            if adaptive:
                choice = chooser.choose(learner.beta, learner.covariance, loop.plant.joint_targets)
                if choice is None:
                    failures.append((i, 'no pose left to choose (pool used up or paths refused)'))
                    break
                pose = choice.joints
                chosen.append(pose)
            t0 = loop.plant.t
            loop.start_move(pose, speed_fraction, stream_rate_hz, pause)
            moved = [None]
            x0 = loop.last_output.x
            # the wheels' ground position (m): where the joints began to move, and the lowest
            # and highest while held (or, for the first move, since the robot sat) and since
            held = stand_span if i == 0 else [x0, x0]
            span = [None, None, None]

            def done(o, moved=moved, span=span, held=held):
                if moved[0] is None and loop.streamer is None and not loop.plant.joints_moving:
                    moved[0] = loop.plant.t
                if span[0] is None:
                    streamer = loop.streamer
                    if streamer is not None and streamer.progress_s == 0.0:
                        held[0], held[1] = min(held[0], o.x), max(held[1], o.x)
                        return o.mode != 'balance'
                    span[:] = [o.x, o.x, o.x]
                span[1], span[2] = min(span[1], o.x), max(span[2], o.x)
                return o.balanced_point is not None or o.mode != 'balance'

            got = loop.run(pose_timeout_s, until=done)
            out = loop.last_output
            travel.append(0.0 if span[0] is None else max(span[0] - span[1], span[2] - span[0]))
            hold_travel.append(0.0 if i == 0 else max(x0 - held[0], held[1] - x0))
            if out.mode != 'balance':
                failures.append((i, f'left balance: {out.mode}'))
                break
            if not got or out.balanced_point is None:
                failures.append((i, 'no balanced point within the timeout'))
                if bar is not None:
                    bar.update(1)
                continue
            p = out.balanced_point
            true_pitch.append(loop.plant.truth().balance_pitch)
            # the points read on the moves since the last pose, learned with the pose's point
            for m in loop.move_points[n_moved:]:
                learner.update(m.q_base, m.joints, sigma=m.q_base_se)
            n_moved = len(loop.move_points)
            if p.q_base_se > 0:  # the detector's standard error, as /balanced_pose carries it
                learner.update(p.q_base, p.joints, sigma=p.q_base_se)
            else:
                learner.update(p.q_base, p.joints)
            beta = learner.beta
            ctl.set_beta(beta)
            betas.append(np.array(beta, float))
            points.append(p)
            idx.append(i)
            t1 = loop.plant.t
            mv = (moved[0] if moved[0] is not None else t1) - t0
            paused = loop.moves[-1].paused_s if loop.moves and stream_rate_hz else 0.0
            timings.append(
                {
                    'move_s': mv,
                    'settle_s': t1 - t0 - mv,
                    'total_s': t1 - t0,
                    'paused_s': paused,
                    'travel_m': travel[-1],
                    'hold_travel_m': hold_travel[-1],
                    'ok': True,
                }
            )
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - wall
    return SessionResult(
        np.array(betas),
        points,
        idx,
        timings,
        true_pitch,
        stood,
        loop.plant.t,
        wall,
        failures,
        loop,
        np.array(chosen) if adaptive else poses,
        travel,
        hold_travel,
        max(x_sit - stand_span[0], stand_span[1] - x_sit),
    )
