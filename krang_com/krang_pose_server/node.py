"""pose_server: the next excitatory pose on /pose_server/next_pose (thin ROS shell).

selection 'adaptive' (default): from a pool of safe, balanced poses (pool_file, or pool_size poses
drawn at start with pool_seed), the pose that most lowers the expected forward CoM error per
second of move and settle, given the estimator's posterior on /com_estimator/posterior
(krang_pose_server.selection). selection 'fixed': the meta-learned list poses_file in order (the
paper's method).

~/next_pose is refused unless the controller balances (its latched mode topic) and while a move is
under way; a move stops where it is if the controller leaves balance. While the controller's
latched balance_converged is false a move holds its setpoint (at most max_pause_s in total per
move, then the rest at slow_fraction of its speed: krang_pose_server.streaming); each pause is
logged, and the next reply and the diagnostics give the pauses of the last move."""

import math
import sys
from dataclasses import dataclass, field

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Float64MultiArray, String
from std_srvs.srv import Trigger

from krang_model.config import config_path
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_core import names, params
from krang_ros import messages, topics
from krang_ros.params import declare
from krang_ros.spin import Polled, run_node, take_waiting

from .pool import PosePool
from .selection import CRITERIA, AdaptiveSelector
from .sequence import PoseSequence, StraightLineMove
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
        ):
            raise ValueError(
                'stream_rate_hz and sigma_pitch_rad must be > 0, pool_size >= 1, settle_s >= 0'
            )


def describe_parameters():
    return params.describe(PoseServerParams)


class PoseServer(Node):
    def __init__(self, **kwargs):
        super().__init__('pose_server', **kwargs)
        self.robot = load_krang()
        cfg = declare(self, PoseServerParams)
        poses_file = cfg.poses_file or str(config_path('excitatory_poses.csv'))
        self.sequence = PoseSequence.from_csv(poses_file, self.robot, KRANG_POSE_COLUMNS)
        self.selection = cfg.selection
        self.speed_fraction = cfg.speed_fraction
        self.selector = None
        self.posterior = None
        self.chosen = 0
        self.mode = None  # the controller's, from its latched mode topic
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
            Float64MultiArray, names.relative(names.POSTERIOR), self.on_posterior, topics.LATCHED
        )
        self.create_subscription(String, names.relative(names.MODE), self.on_mode, topics.LATCHED)
        self.create_subscription(
            Bool, names.relative(names.BALANCE_CONVERGED), self.on_converged, topics.LATCHED
        )
        self.pause = PauseConfig(cfg.max_pause_s, cfg.slow_fraction)
        self.converged = None  # the controller's flag; unknown = do not wait
        self.stream_rate = cfg.stream_rate_hz
        self.measured = None
        self.move = None  # the MoveStreamer under way
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

    def on_posterior(self, msg):
        n = self.robot.n_beta
        data = np.asarray(msg.data, dtype=float)
        if data.size != (n + 1) * n:
            self.get_logger().error(
                f'posterior of {data.size} numbers ignored (needs {(n + 1) * n})'
            )
            return
        data = data.reshape(n + 1, n)
        self.posterior = (data[0], data[1:])

    def _next_target(self, start):
        """(joints, text) of the next pose, or (None, why not)."""
        if self.selector is None:
            target = self.sequence.advance()
            if target is None:
                return None, (
                    f'no poses left (all {len(self.sequence)} done); call '
                    f'{names.POSE_RESET} to start over'
                )
            return target.joints, target.describe()
        if self.posterior is None:
            return None, f'no posterior from com_estimator yet ({names.POSTERIOR})'
        beta, cov = self.posterior
        if not np.any(cov):
            return None, 'the estimator reports no covariance: use selection:=fixed with it'
        choice = self.selector.choose(beta, cov, start)
        if choice is None:
            refused = self.selector.refused
            why = f' ({refused} refused: their path collides)' if refused else ''
            return None, f'pool used up{why}; call {names.POSE_RESET} to start over'
        self.chosen += 1
        return choice.joints, (
            f'adaptive pose {self.chosen} (pool pose {choice.index}; '
            f'predicted RMS forward error {1000 * choice.rms_before_m:.2f} -> '
            f'{1000 * choice.rms_after_m:.2f} mm; predicted pitch {choice.margin_rad:.2f} rad '
            'above the caster at worst on the way, less 2 std)'
        )

    def on_mode(self, msg):
        self.mode = msg.data
        if self.move is not None and self.mode != 'balance':
            self.get_logger().warning(f'controller left balance ({self.mode}): the move stops')
            self.move = None

    def on_converged(self, msg):
        self.converged = bool(msg.data)

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
        move = self.move
        if move is None:
            return
        now = self.now()
        event = move.advance(max(now - self.last_tick, 0.0), self.converged is not False)
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
        self.cmd_pub.publish(
            messages.joint_state(
                self.get_clock().now().to_msg(), self.robot.pose_joints, move.setpoint
            )
        )
        if move.done:
            self.get_logger().info(f'move done ({move.summary()})')
            self.last_move, self.move = move, None

    def on_next_pose(self, request, response):
        if self.mode != 'balance':
            response.success = False
            response.message = (
                f'refused: the robot is not balancing (controller mode: '
                f'{self.mode or "unknown"}); stand it up first'
            )
            return response
        if self.move is not None:
            response.success = False
            response.message = 'refused: a move is still under way'
            return response
        start = self.measured_joints()
        goal, text = self._next_target(
            start if start is not None else np.zeros(len(self.robot.pose_joints))
        )
        if goal is None:
            response.success = False
            response.message = text
            return response
        start = goal if start is None else start
        plan = StraightLineMove.plan(start, goal, self.robot.velocity_limit, self.speed_fraction)
        self.move = MoveStreamer(plan, self.pause)
        self.last_tick = self.now()
        self.target_pub.publish(
            messages.joint_state(self.get_clock().now().to_msg(), self.robot.pose_joints, goal)
        )
        self.stream_move()
        response.success = True
        response.message = f'{text} (a move of {plan.duration:.1f} s)'
        if self.last_move is not None:
            response.message += f'; the last move: {self.last_move.summary()}'
        self.get_logger().info(f'commanding {response.message}')
        return response

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
