"""pose_server: the move to the next excitatory pose (thin ROS shell).

selection 'adaptive' (default): from a pool of safe, balanced poses (pool_file, or pool_size poses
drawn at start with pool_seed), the pose that most lowers the expected forward CoM error per
second of move and settle, given the estimator's mass model and its covariance on
/com_estimator/beta (krang_pose_server.selection). selection 'fixed': the meta-learned list
poses_file in order (the paper's method).

Two ways start the same move (start_move): the action ~/move_to_next_pose (MoveToNextPose: feedback
while it moves, the balanced pose that ends it as the result, cancel) and the service ~/next_pose
(Trigger: answers once the move has started). Both are refused unless the controller balances (its
latched mode topic) and while a move is under way (or, for a goal, waits for its balanced pose); a
move stops and holds where it is (as on cancel) if the controller leaves balance. While the
controller's latched balance_converged is false a move holds its setpoint (at most max_pause_s in
total per move, then the rest at slow_fraction of its speed: krang_pose_server.streaming); each
pause is logged, and the next reply and the diagnostics give the pauses of the last move. A
cancelled goal stops the move where it is: that setpoint becomes the target, commanded once more,
and the controller balances the robot there. An arm fault (/can_bridge/arm_fault: an arm module
stopped answering) stops a move the same way (the bridge sends nothing to the silent module, which
holds by itself) and ends its goal with the reason; while it is latched, moves are refused with it
until /can_bridge/recover clears it.

After a stand-up caught back on its caster the waist is re-posed by the controller's estimate
(repose.py): a move that does not wait for balance_converged (the robot sits) and stops and holds
where it is if the controller leaves sit."""

import math
import sys
from dataclasses import dataclass, field

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray
from krang_com_interfaces.action import MoveToNextPose
from krang_com_interfaces.msg import (
    ArmFault,
    BalancedPose,
    ControllerMode,
    MassModel,
    StandEstimate,
)
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from krang_model.com import balance_pitch
from krang_model.config import config_path
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_core import message_values, names, params
from krang_core.pitch import pitch_from_quaternion
from krang_ros import messages, topics, wire
from krang_ros.actions import HeldGoals, goal_key
from krang_ros.params import declare
from krang_ros.spin import Polled, run_node, take_latest, take_waiting, without_qos_events

from .pool import PosePool
from .repose import ReposeAfterCaughtStand
from .selection import CRITERIA, AdaptiveSelector
from .sequence import MAX_BALANCE_RATE_RAD_S, PoseSequence, StraightLineMove
from .streaming import MoveStreamer, PauseConfig


def _doc(default, text):
    return field(default=default, metadata={'doc': text})


@dataclass(frozen=True)
class PoseServerParams:
    """pose_server's parameters (read at start)."""

    selection: str = _doc(
        'adaptive',
        "'adaptive' (from the pool, by the estimator's posterior) "
        "or 'fixed' (poses_file in order, the paper's method)",
    )
    poses_file: str = _doc('', "the fixed list ('' = config/excitatory_poses.csv)")
    pool_file: str = _doc('', "adaptive: pose CSV of the pool ('' = draw pool_size poses)")
    pool_size: int = _doc(1000, 'adaptive: safe, balanced poses drawn at start, >= 1')
    pool_seed: int = _doc(0, 'adaptive: seed of that draw')
    criterion: str = _doc('forward', 'adaptive: ' + ' | '.join(CRITERIA))
    sigma_pitch_rad: float = _doc(
        math.radians(0.1), "adaptive: a balanced pose's pitch noise, rad, > 0"
    )
    settle_s: float = _doc(12.0, 'adaptive: time to settle and learn after a move, s, >= 0')
    speed_fraction: float = _doc(
        0.8, "moves run at this fraction of the joints' speed limits, (0, 1]"
    )
    max_balance_rate_rad_s: float = _doc(
        MAX_BALANCE_RATE_RAD_S,
        'a move is slowed so that the balance pitch its path predicts (with the current beta) '
        'moves at most this fast, rad/s; 0 = the joint speed alone',
    )
    stream_rate_hz: float = _doc(20.0, 'rate of the streamed joint targets during a move, > 0')
    max_pause_s: float = _doc(
        PauseConfig.max_pause_s,
        "a move holds while the controller's balance_converged is false, at most this long in "
        'total, s, >= 0',
    )
    slow_fraction: float = _doc(
        PauseConfig.slow_fraction,
        'after max_pause_s of pauses the rest of the move runs at this fraction of its speed, '
        '(0, 1]',
    )
    repose_after_caught_stand: bool = _doc(
        True,
        "after a stand-up caught back on its caster, move the waist by the controller's "
        'CoM-angle error estimate (its stand_estimate) before it retries',
    )

    def __post_init__(self):
        PauseConfig(self.max_pause_s, self.slow_fraction)  # checks them
        if self.selection not in ('adaptive', 'fixed'):
            raise ValueError(f"selection must be 'adaptive' or 'fixed', got {self.selection!r}")
        if self.criterion not in CRITERIA:
            raise ValueError(f'criterion must be one of {CRITERIA}, got {self.criterion!r}')
        if not 0 < self.speed_fraction <= 1:
            raise ValueError(f'speed_fraction must be in (0, 1], got {self.speed_fraction}')
        if not (
            self.stream_rate_hz > 0
            and self.sigma_pitch_rad > 0
            and self.pool_size >= 1
            and self.settle_s >= 0
            and self.max_balance_rate_rad_s >= 0
        ):
            raise ValueError(
                'stream_rate_hz and sigma_pitch_rad must be > 0, pool_size >= 1, settle_s and '
                'max_balance_rate_rad_s >= 0'
            )


def describe_parameters():
    return params.describe(PoseServerParams)


@dataclass
class MoveGoal:
    """A move_to_next_pose goal while it is active."""

    handle: object  # its ServerGoalHandle
    target: np.ndarray
    expected_gain: float  # [m]; NaN if unknown
    text: str  # what start_move said
    settling: bool = False  # the move reached its target: the next balanced pose ends the goal
    cancel_requested: bool = False
    imu: object = None  # a Polled /imu/data subscription for the feedback's pitch, while active
    pitch: float = math.nan


class PoseServer(ReposeAfterCaughtStand, Node):
    def __init__(self, **kwargs):
        super().__init__('pose_server', **kwargs)
        self.robot = load_krang()
        cfg = declare(self, PoseServerParams)
        poses_file = cfg.poses_file or str(config_path('excitatory_poses.csv'))
        self.sequence = PoseSequence.from_csv(poses_file, self.robot, KRANG_POSE_COLUMNS)
        self.selection = cfg.selection
        self.speed_fraction = cfg.speed_fraction
        self.max_balance_rate = cfg.max_balance_rate_rad_s
        self.selector = None
        self.posterior = None  # (beta, covariance or None) from /com_estimator/beta
        self.chosen = 0
        self.expected_gain = math.nan  # of the pose start_move chose last [m]
        self.mode = None  # the controller's, from its latched mode topic
        self.mode_stamp = None  # ... and that message's stamp
        if self.selection == 'adaptive':
            self.selector = self._make_selector(cfg)
        else:
            self.get_logger().info(f'{len(self.sequence)} poses from {poses_file}')
        qos = topics.QOS
        self.cmd_pub = self.create_publisher(
            JointState, names.relative(names.JOINT_POSITION_CMD), qos[names.JOINT_POSITION_CMD]
        )
        self.target_pub = self.create_publisher(
            JointState, names.private(names.POSE_TARGET), qos[names.POSE_TARGET]
        )
        self.diag_pub = self.create_publisher(
            DiagnosticArray, names.relative(names.DIAGNOSTICS), qos[names.DIAGNOSTICS]
        )
        self.create_service(Trigger, names.private(names.NEXT_POSE), self.on_next_pose)
        self.create_service(Trigger, names.private(names.POSE_RESET), self.on_reset)
        self.goal = None  # the active MoveGoal
        self.move_action = HeldGoals(
            self,
            MoveToNextPose,
            names.private(names.MOVE_TO_NEXT_POSE),
            self.on_goal,
            self.on_cancel,
            MutuallyExclusiveCallbackGroup(),
        )
        # read when a move is planned (measured_joints), not by a callback: the executor would
        # wake for every sample (100-500 Hz) to keep one of them
        self.joint_sub = self.create_subscription(
            JointState,
            names.relative(names.JOINT_STATES),
            lambda msg: None,
            qos[names.JOINT_STATES],
            callback_group=Polled(),
        )
        self.create_subscription(
            MassModel, names.relative(names.BETA), self.on_mass_model, topics.QOS[names.BETA]
        )
        self.create_subscription(
            ControllerMode, names.relative(names.MODE), self.on_mode, topics.LATCHED
        )
        self.create_subscription(
            BalancedPose,
            names.relative(names.BALANCED_POSE),
            self.on_balanced_pose,
            qos[names.BALANCED_POSE],
        )
        self.create_subscription(
            Bool, names.relative(names.BALANCE_CONVERGED), self.on_converged, topics.LATCHED
        )
        self.stand_estimate = None  # a caught stand-up's StandEstimate, until acted on
        if cfg.repose_after_caught_stand:
            self.create_subscription(
                StandEstimate,
                names.relative(names.STAND_ESTIMATE),
                self.on_stand_estimate,
                qos[names.STAND_ESTIMATE],
            )
        self.arm_fault = ''  # the bridge's latched arm fault; '' when clear
        self.create_subscription(
            ArmFault, names.relative(names.ARM_FAULT), self.on_arm_fault, topics.LATCHED
        )
        self.pause = PauseConfig(cfg.max_pause_s, cfg.slow_fraction)
        self.converged = None  # the controller's flag; unknown = do not wait
        self.stream_rate = cfg.stream_rate_hz
        self.measured = None
        self.move = None  # the MoveStreamer under way
        self.reposing = False  # ... is the re-pose of a sitting robot (no balance to wait for)
        self.target = None  # the pose of the last move started
        self.last_move = None  # ... and the one before, for its pauses
        self.last_tick = None
        self.create_timer(1.0 / self.stream_rate, self.stream_move)
        self.create_timer(1.0, self.publish_diagnostics)

    def _make_selector(self, cfg):
        # every move's path is checked for floor and self-collision at the balance pitch the
        # current beta predicts: a straight joint line between two safe poses can still drive a
        # gripper into the floor
        self.pose_pool = PosePool(self.robot)
        if cfg.pool_file:
            _, joints, _ = load_poses(
                cfg.pool_file, KRANG_POSE_COLUMNS, (self.robot.lower, self.robot.upper)
            )
            source = cfg.pool_file
        else:
            joints = self.pose_pool.generate(cfg.pool_size, seed=cfg.pool_seed).joints
            source = f'{cfg.pool_size} safe, balanced poses drawn with seed {cfg.pool_seed}'
        selector = AdaptiveSelector(
            self.robot,
            joints,
            sigma_pitch_rad=cfg.sigma_pitch_rad,
            criterion=cfg.criterion,
            settle_s=cfg.settle_s,
            speed_fraction=self.speed_fraction,
            path_check=self.pose_pool.path_clear,
        )
        self.get_logger().info(f'adaptive pose selection ({selector.criterion}) from {source}')
        return selector

    def on_mass_model(self, msg):
        values = message_values.mass_model_values(msg, self.robot.n_beta)
        if values is None:
            self.get_logger().error(
                f'mass model of {len(msg.beta)} values or with NaN/inf ignored '
                f'(needs {self.robot.n_beta})'
            )
            return
        self.posterior = values

    def _next_target(self, start):
        """(joints, text) of the next pose, or (None, why not)."""
        self.expected_gain = math.nan
        if self.selector is None:
            target = self.sequence.advance()
            if target is None:
                return None, (
                    f'no poses left (all {len(self.sequence)} done); call '
                    f'{names.POSE_RESET} to start over'
                )
            return target.joints, target.describe()
        if self.posterior is None:
            return None, f'no mass model from com_estimator yet ({names.BETA})'
        beta, cov = self.posterior
        if cov is None or not np.any(cov):
            return None, 'the estimator reports no covariance: use selection:=fixed with it'
        choice = self.selector.choose(beta, cov, start)
        if choice is None:
            refused = self.selector.refused
            why = f' ({refused} refused: their path collides)' if refused else ''
            return None, f'pool used up{why}; call {names.POSE_RESET} to start over'
        self.chosen += 1
        self.expected_gain = choice.rms_before_m - choice.rms_after_m  # NaN unless 'forward'
        return choice.joints, (
            f'adaptive pose {self.chosen} (pool pose {choice.index}; '
            f'predicted RMS forward error {1000 * choice.rms_before_m:.2f} -> '
            f'{1000 * choice.rms_after_m:.2f} mm; predicted pitch {choice.margin_rad:.2f} rad '
            'above the caster at worst on the way, less 2 std)'
        )

    def on_mode(self, msg):
        self.mode, self.mode_stamp = message_values.mode_name(msg), msg.header.stamp
        if self.move is not None and self.reposing:
            if self.mode != 'sit':
                self.get_logger().warning(f'controller left sit ({self.mode}): the re-pose stops')
                self.stop_and_hold()
            return
        if self.mode != 'balance':
            if self.move is not None:
                self.get_logger().warning(f'controller left balance ({self.mode}): the move stops')
                self.stop_and_hold()
            if self.goal is not None:
                self.end_goal(
                    False, f'the controller left balance ({self.mode}): the move stopped'
                )
        if self.mode == 'sit':
            self.repose_if_due()

    def on_converged(self, msg):
        self.converged = bool(msg.data)

    def arm_refusal(self):
        return f'{self.arm_fault}: recover with {names.BRIDGE_RECOVER}'

    def on_arm_fault(self, msg):
        """An arm module stopped answering: a move stops and holds where it is (as on cancel),
        its goal ends with the reason; cleared: moves are accepted again."""
        reason, was = message_values.arm_fault_reason(msg), self.arm_fault
        self.arm_fault = reason
        if not reason:
            if was:
                self.get_logger().info(f'arm fault cleared ({was}): moves accepted again')
            return
        if reason == was:
            return
        self.get_logger().error(f'arm fault: {self.arm_refusal()}')
        stopped = 'the move had reached its target'
        if self.move is not None:
            done = self.stop_and_hold()
            stopped = f'the move stopped at {done:.0%} of its path, holding there'
        if self.goal is not None:
            self.end_goal(False, f'{stopped}: {self.arm_refusal()}')

    def measured_joints(self):
        """The body joints of the newest /joint_states that has them all, among those waiting
        (the QoS depth: the last 10 samples); the last known ones if none of them has; None before
        the first."""
        for msg in reversed(take_waiting(self.joint_sub)):
            joints = messages.joints_from_state(msg, self.robot.pose_joints)
            if joints is not None:
                self.measured = joints
                break
        return self.measured

    def now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def stream_move(self):
        """At stream_rate_hz: the move's next setpoint, the goal's feedback and its cancel (and
        a re-pose waiting for the first /joint_states)."""
        if self.stand_estimate is not None:
            self.repose_if_due()
        goal = self.goal
        if goal is not None and goal.cancel_requested:
            self.stop_for_cancel(goal)
            return
        move = self.move
        if move is None:
            if goal is not None:
                self.publish_feedback(goal, 1.0, False)
            return
        now = self.now()
        balanced = self.reposing or self.converged is not False
        event = move.advance(max(now - self.last_tick, 0.0), balanced)
        self.last_tick = now
        if event == 'pause':
            self.get_logger().info(
                'move paused: the controller reports an unconverged balance estimate '
                f'({move.summary()} so far)'
            )
        elif event == 'resume':
            self.get_logger().info(f'move resumed ({move.summary()})')
        elif event == 'slow':
            self.get_logger().warning(
                f'move paused {self.pause.max_pause_s:g} s in total: the rest at '
                f'{self.pause.slow_fraction:g} of its speed'
            )
        self.command(move.setpoint)
        if move.done:
            self.get_logger().info(f'move done ({move.summary()})')
            self.last_move, self.move = move, None
            if goal is not None:
                goal.settling = True
        if goal is not None:
            duration = move.move.duration
            progress = 1.0 if duration <= 0 else move.progress_s / duration
            self.publish_feedback(goal, progress, move.paused)

    def command(self, joints):
        self.cmd_pub.publish(
            messages.joint_state(self.get_clock().now().to_msg(), self.robot.pose_joints, joints)
        )

    def start_move(self):
        """The move to the next pose, started: (True, what it is) or (False, why not). The one
        way next_pose and move_to_next_pose move the robot."""
        if self.mode != 'balance':
            return False, (
                f'refused: the robot is not balancing (controller mode: '
                f'{self.mode or "unknown"}); stand it up first'
            )
        if self.arm_fault:
            return False, f'refused: {self.arm_refusal()}'
        if self.move is not None:
            return False, 'refused: a move is still under way'
        if self.goal is not None:
            return False, 'refused: a move is still under way (waiting for its balanced pose)'
        start = self.measured_joints()
        goal, text = self._next_target(
            start if start is not None else np.zeros(len(self.robot.pose_joints))
        )
        if goal is None:
            return False, text
        plan = self.begin_move(goal if start is None else start, goal)
        message = f'{text} (a move of {plan.duration:.1f} s)'
        if self.last_move is not None:
            message += f'; the last move: {self.last_move.summary()}'
        self.get_logger().info(f'commanding {message}')
        return True, message

    def begin_move(self, start, goal, reposing=False):
        """The straight-line move from `start` to `goal`, planned and streamed from now (its
        first setpoint at once); `reposing`: a sitting robot's re-pose, which does not wait for
        balance_converged. Returns its plan."""
        beta = self.robot.nominal_beta if self.posterior is None else self.posterior[0]
        plan = StraightLineMove.plan(
            start,
            goal,
            self.robot.velocity_limit,
            self.speed_fraction,
            balance=lambda joints: balance_pitch(self.robot, joints, beta),
            max_balance_rate=self.max_balance_rate,
        )
        self.move, self.reposing = MoveStreamer(plan, self.pause), reposing
        self.target = np.array(goal, dtype=float)
        self.last_tick = self.now()
        self.publish_target(goal)
        self.stream_move()
        return plan

    def publish_target(self, joints):
        self.target_pub.publish(
            messages.joint_state(self.get_clock().now().to_msg(), self.robot.pose_joints, joints)
        )

    def on_next_pose(self, request, response):
        response.success, response.message = self.start_move()
        return response

    # ---- the move_to_next_pose action -----------------------------------------------------------
    def on_goal(self, handle):
        """A goal, accepted: the move started, or the goal ended at once with why not."""
        ok, message = self.start_move()
        if not ok:
            self.get_logger().warning(f'move_to_next_pose: {message}')
            self.move_action.end(handle, False, message=message)
            return
        # a move of no length is done as it starts: the next balanced pose ends the goal
        self.goal = MoveGoal(
            handle, self.target, self.expected_gain, message, settling=self.move is None
        )
        # the feedback's pitch, read only while a goal is active: one more reader of the 500 Hz
        # /imu/data would cost the bridge's publication on the control path all the time
        self.goal.imu = self.create_subscription(
            Imu,
            names.relative(names.IMU),
            lambda raw: None,
            topics.LATEST,
            raw=True,
            callback_group=Polled(),
        )
        without_qos_events(self)

    def on_cancel(self, handle):
        """Accepted for the active goal: stream_move stops the move at its next tick."""
        if self.goal is None or goal_key(self.goal.handle) != goal_key(handle):
            return False
        self.goal.cancel_requested = True
        return True

    def stop_for_cancel(self, goal):
        """The move stops at its setpoint, which becomes the target: the robot holds that pose
        and the controller balances it there."""
        if self.move is None:
            self.end_goal(False, 'cancelled: the move had reached its target', True)
            return
        done = self.stop_and_hold()
        self.end_goal(
            False, f'cancelled: the move stopped at {done:.0%} of its path, holding there', True
        )

    def stop_and_hold(self):
        """The move under way stops at its setpoint, which becomes the target, commanded once
        more; returns the fraction of its path done."""
        move = self.move
        self.last_move, self.move = move, None
        held = move.setpoint
        self.publish_target(held)
        self.command(held)
        done = 1.0 if move.move.duration <= 0 else move.progress_s / move.move.duration
        self.get_logger().info(f'move stopped at {done:.0%} of its path ({move.summary()})')
        return done

    def on_balanced_pose(self, msg):
        goal = self.goal
        if goal is not None and goal.settling and not msg.in_motion:  # a move ends at rest
            self.end_goal(
                True,
                f'balanced at base pitch {msg.base_pitch:+.4f} rad: {goal.text}',
                balanced_pose=msg,
            )

    def publish_feedback(self, goal, progress, paused):
        raw = take_latest(goal.imu)
        if raw is not None:
            try:
                goal.pitch = pitch_from_quaternion(*wire.read_imu(raw).orientation)
            except wire.WireError:
                pass
        self.move_action.feedback(
            goal.handle,
            progress=float(progress),
            base_pitch=goal.pitch,
            paused_for_balance=bool(paused),
            expected_gain=goal.expected_gain,
        )

    def end_goal(self, success, message, cancelled=False, **fields):
        goal, self.goal = self.goal, None
        self.destroy_subscription(goal.imu)
        self.move_action.end(
            goal.handle,
            success,
            cancelled,
            message=message,
            target=[float(v) for v in goal.target],
            **fields,
        )
        if success:
            self.get_logger().info(f'move_to_next_pose: {message}')
        else:
            self.get_logger().warning(f'move_to_next_pose: {message}')

    def on_reset(self, request, response):
        self.sequence.reset()
        if self.selector is not None:
            self.selector.reset()
            self.chosen = 0
        response.success = True
        response.message = (
            f'back to the start of {len(self.sequence)} poses'
            if self.selector is None
            else 'every pool pose available again'
        )
        self.get_logger().info(response.message)
        return response

    def publish_diagnostics(self):
        if self.selector is not None:
            text = f'adaptive: {self.chosen} poses chosen from {len(self.selector.pool)}'
            values = {'chosen': self.chosen, 'pool': len(self.selector.pool)}
        else:
            current = self.sequence.current()
            if current:
                text = current.describe()
            else:
                text = f'waiting for next_pose ({len(self.sequence)} poses)'
            values = {'cursor': self.sequence.cursor, 'total': len(self.sequence)}
        shown = self.move or self.last_move
        if shown is not None:
            values['pauses'] = shown.pauses
            values['paused_s'] = f'{shown.paused_s:.1f}'
        self.diag_pub.publish(
            messages.diagnostics(
                self.get_clock().now().to_msg(), 'pose_server', 'ok', text, values
            )
        )


def main(args=None):
    return run_node(PoseServer, args)


if __name__ == '__main__':
    sys.exit(main())
