"""com_estimator: learns beta from /balanced_pose and publishes it (thin shell over OnlineLearner).

Subscribes /balanced_pose (krang_com_interfaces/BalancedPose). Publishes ~/beta (MassModel,
latched: beta with its posterior covariance, which the pose server's adaptive choice reads) and
~/com (the CoM at each learned pose, in base_footprint); serves ~/save (writes `output`
atomically) and ~/reset."""

import sys
from dataclasses import dataclass, field
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from krang_com_interfaces.msg import BalancedPose, MassModel
from rclpy.node import Node
from std_srvs.srv import Trigger

from krang_model.beta import load_beta, save_beta
from krang_model.robot import load_krang
from krang_core import names, params
from krang_core.message_values import balanced_pose_values
from krang_ros import messages, topics
from krang_ros.robot_frames import BASE_FOOTPRINT
from krang_ros.params import declare
from krang_ros.spin import run_node

from .registry import estimator_names
from .online import OnlineLearner


@dataclass(frozen=True)
class EstimatorParams:
    """com_estimator's parameters (read at start)."""

    method: str = field(
        default='map-online',
        metadata={
            'doc': 'estimator of the registry (krang_com_estimator.registry): '
            + ' | '.join(estimator_names())
        },
    )
    initial_beta: str = field(
        default='', metadata={'doc': "beta file to start from ('' = the URDF's nominal beta)"}
    )
    output: str = field(
        default='beta.yaml',
        metadata={
            'doc': "where ~/save writes the learned beta (.yaml, .json or the authors' .txt)"
        },
    )

    def __post_init__(self):
        if self.method not in estimator_names():
            raise ValueError(f'method must be one of {estimator_names()}, got {self.method!r}')


def describe_parameters():
    return params.describe(EstimatorParams)


class ComEstimatorNode(Node):
    def __init__(self, **kwargs):
        super().__init__('com_estimator', **kwargs)
        self.robot = load_krang()
        cfg = declare(self, EstimatorParams)
        method, beta_file, self.output = cfg.method, cfg.initial_beta, Path(cfg.output)
        beta0 = load_beta(beta_file, self.robot) if beta_file else self.robot.nominal_beta
        self.learner = OnlineLearner(self.robot, beta0, method)
        qos = topics.QOS
        self.beta_pub = self.create_publisher(
            MassModel, names.private(names.BETA), qos[names.BETA]
        )
        self.com_pub = self.create_publisher(
            PointStamped, names.private(names.COM), qos[names.COM]
        )
        self.diag_pub = self.create_publisher(
            DiagnosticArray, names.relative(names.DIAGNOSTICS), qos[names.DIAGNOSTICS]
        )
        self.create_subscription(
            BalancedPose,
            names.relative(names.BALANCED_POSE),
            self.on_balanced_pose,
            qos[names.BALANCED_POSE],
        )
        self.create_service(Trigger, names.private(names.SAVE), self.on_save)
        self.create_service(Trigger, names.private(names.ESTIMATOR_RESET), self.on_reset)
        self.create_timer(1.0, self.publish_diagnostics)
        self.rejected = 0
        self.publish_beta()
        self.get_logger().info(
            f'estimator {method}, initial beta {beta_file or "nominal (URDF)"}, saves to '
            f'{self.output}'
        )

    def on_balanced_pose(self, msg):
        pose = balanced_pose_values(msg, self.robot.pose_joints)
        if pose is None:
            self.rejected += 1
            self.get_logger().error(
                'rejected balanced pose: needs every body joint and the base pitch, finite '
                f'(got {list(msg.joint_names)})'
            )
            return
        try:
            beta = self.learner.add_balanced_pose(
                pose.q_base, pose.joints, pose.q_base_se, pose.in_motion
            )
        except ValueError as err:
            self.rejected += 1
            self.get_logger().error(f'rejected balanced pose: {err}')
            return
        if pose.in_motion:  # its beta goes out with the next pose's
            self.get_logger().debug(f'point read while moving: pitch {pose.q_base:+.5f} rad')
            return
        self.publish_beta()
        com = self.learner.com(pose.q_base, pose.joints)
        point = PointStamped()
        point.header = msg.header
        point.header.frame_id = BASE_FOOTPRINT  # frame 0 (the axle) is one wheel radius above it
        point.point.x, point.point.y = float(com[0]), float(com[1])
        point.point.z = float(com[2]) + self.robot.wheel_radius
        self.com_pub.publish(point)
        self.get_logger().info(
            f'pose {len(self.learner.poses)}: CoM x {1000 * com[0]:+.2f} mm at the measured '
            f'pitch; total mass {beta[0::4].sum():.2f} kg'
        )

    def publish_beta(self):
        beta, cov = self.learner.posterior()
        self.beta_pub.publish(
            messages.mass_model(
                self.get_clock().now().to_msg(),
                self.robot.body_names,
                beta,
                cov,
                source=self.learner.method,
                poses=len(self.learner.poses),
            )
        )

    def on_save(self, request, response):
        path = save_beta(
            self.output,
            self.learner.beta,
            self.robot,
            method=self.learner.method,
            poses=len(self.learner.poses),
        )
        response.success, response.message = (
            True,
            f'saved beta after {len(self.learner.poses)} poses and '
            f'{self.learner.moving_points} points read while moving to {path}',
        )
        self.get_logger().info(response.message)
        return response

    def on_reset(self, request, response):
        self.learner.reset()
        self.publish_beta()
        response.success, response.message = True, 'beta reset to the initial estimate'
        self.get_logger().info(response.message)
        return response

    def publish_diagnostics(self):
        self.diag_pub.publish(
            messages.diagnostics(
                self.get_clock().now().to_msg(),
                'com_estimator',
                'ok' if not self.rejected else 'warn',
                f'{len(self.learner.poses)} poses learned',
                {
                    'poses': len(self.learner.poses),
                    'points_while_moving': self.learner.moving_points,
                    'rejected': self.rejected,
                    'method': self.learner.method,
                },
            )
        )


def main(args=None):
    return run_node(ComEstimatorNode, args)


if __name__ == '__main__':
    sys.exit(main())
