"""pose_server: the next excitatory pose on /pose_server/next_pose (thin ROS shell).

selection 'adaptive' (default): from a pool of safe, balanced poses (pool_file, or pool_size poses
drawn at start with pool_seed), the pose that most lowers the expected forward CoM error per
second of move and settle, given the estimator's posterior on /com_estimator/posterior
(krang_pose_server.selection). selection 'fixed': the meta-learned list poses_file in order (the
paper's method)."""
import sys

import numpy as np

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from krang_com_estimator.online import POSTERIOR

from krang_model.config import config_path
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_ros import messages, names, topics
from krang_ros.spin import run_node

from .pool import generate_pool
from .selection import AdaptiveSelector
from .sequence import PoseSequence, StraightLineMove


class PoseServer(Node):
    def __init__(self):
        super().__init__('pose_server')
        self.robot = load_krang()
        p = self.declare_parameter
        poses_file = p('poses_file', '').value or str(config_path('excitatory_poses.csv'))
        self.sequence = PoseSequence.from_csv(poses_file, self.robot, KRANG_POSE_COLUMNS)
        self.selection = p('selection', 'adaptive').value
        self.speed_fraction = p('speed_fraction', 0.8).value
        self.selector = None
        self.posterior = None
        self.chosen = 0
        if self.selection == 'adaptive':
            self.selector = self._make_selector(p)
        elif self.selection != 'fixed':
            raise ValueError(f"selection must be 'adaptive' or 'fixed', not {self.selection!r}")
        else:
            self.get_logger().info(f'{len(self.sequence)} poses from {poses_file}')
        qos = topics.QOS
        self.cmd_pub = self.create_publisher(JointState, names.JOINT_POSITION_CMD,
                                             qos[names.JOINT_POSITION_CMD])
        self.target_pub = self.create_publisher(JointState, names.POSE_TARGET,
                                                qos[names.POSE_TARGET])
        self.diag_pub = self.create_publisher(DiagnosticArray, names.DIAGNOSTICS,
                                              qos[names.DIAGNOSTICS])
        self.create_service(Trigger, names.NEXT_POSE, self.on_next_pose)
        self.create_service(Trigger, names.POSE_RESET, self.on_reset)
        self.create_subscription(JointState, names.JOINT_STATES, self.on_joint_states,
                                 qos[names.JOINT_STATES])
        self.create_subscription(Float64MultiArray, POSTERIOR, self.on_posterior, topics.LATCHED)
        self.stream_rate = p('stream_rate_hz', 20.0).value
        self.measured = None
        self.move = None
        self.move_started = None
        self.create_timer(1.0 / self.stream_rate, self.stream_move)
        self.create_timer(1.0, self.publish_diagnostics)

    def _make_selector(self, p):
        pool_file = p('pool_file', '').value
        if pool_file:
            _, joints, _ = load_poses(pool_file, KRANG_POSE_COLUMNS)
            source = pool_file
        else:
            n, seed = p('pool_size', 1000).value, p('pool_seed', 0).value
            joints = generate_pool(n, seed=seed, robot=self.robot).joints
            source = f'{n} safe, balanced poses drawn with seed {seed}'
        sigma = p('sigma_pitch_rad', float(np.radians(0.1))).value
        selector = AdaptiveSelector(self.robot, joints, sigma_pitch_rad=sigma,
                                    criterion=p('criterion', 'forward').value,
                                    settle_s=p('settle_s', 12.0).value,
                                    speed_fraction=self.speed_fraction)
        self.get_logger().info(f'adaptive pose selection ({selector.criterion}) from {source}')
        return selector

    def on_posterior(self, msg):
        n = self.robot.n_beta
        data = np.asarray(msg.data, dtype=float)
        if data.size != (n + 1) * n:
            self.get_logger().error(f'posterior of {data.size} numbers ignored '
                                    f'(needs {(n + 1) * n})')
            return
        data = data.reshape(n + 1, n)
        self.posterior = (data[0], data[1:])

    def _next_target(self, start):
        """(joints, text) of the next pose, or (None, why not)."""
        if self.selector is None:
            target = self.sequence.advance()
            if target is None:
                return None, (f'no poses left (all {len(self.sequence)} done); call '
                              f'{names.POSE_RESET} to start over')
            return target.joints, target.describe()
        if self.posterior is None:
            return None, f'no posterior from com_estimator yet ({POSTERIOR})'
        beta, cov = self.posterior
        if not np.any(cov):
            return None, 'the estimator reports no covariance: use selection:=fixed with it'
        choice = self.selector.choose(beta, cov, start)
        if choice is None:
            return None, f'pool used up; call {names.POSE_RESET} to start over'
        self.chosen += 1
        return choice.joints, (f'adaptive pose {self.chosen} (pool pose {choice.index}; '
                               f'predicted RMS forward error {1000 * choice.rms_before_m:.2f} -> '
                               f'{1000 * choice.rms_after_m:.2f} mm)')

    def on_joint_states(self, msg):
        joints = messages.joints_from_state(msg, self.robot.pose_joints)
        if joints is not None:
            self.measured = joints

    def now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def stream_move(self):
        if self.move is None:
            return
        t = self.now() - self.move_started
        self.cmd_pub.publish(messages.joint_state(self.get_clock().now().to_msg(),
                                                  self.robot.pose_joints, self.move.at(t)))
        if t >= self.move.duration:
            self.move = None

    def on_next_pose(self, request, response):
        start = self.measured if self.measured is not None else (
            self.move.goal if self.move else None)
        goal, text = self._next_target(start if start is not None else
                                       np.zeros(len(self.robot.pose_joints)))
        if goal is None:
            response.success = False
            response.message = text
            return response
        start = goal if start is None else start
        self.move = StraightLineMove.plan(start, goal, self.robot.velocity_limit,
                                          self.speed_fraction)
        self.move_started = self.now()
        self.target_pub.publish(messages.joint_state(self.get_clock().now().to_msg(),
                                                     self.robot.pose_joints, goal))
        duration = self.move.duration
        self.stream_move()
        response.success = True
        response.message = f'{text} (moving for {duration:.1f} s)'
        self.get_logger().info(f'commanding {response.message}')
        return response

    def on_reset(self, request, response):
        self.sequence.reset()
        if self.selector is not None:
            self.selector.reset()
            self.chosen = 0
        response.success = True
        response.message = (f'back to the start of {len(self.sequence)} poses'
                            if self.selector is None else 'every pool pose available again')
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
        self.diag_pub.publish(messages.diagnostics(
            self.get_clock().now().to_msg(), 'pose_server', 'ok', text, values))


def main(args=None):
    return run_node(PoseServer, args)


if __name__ == '__main__':
    sys.exit(main())
