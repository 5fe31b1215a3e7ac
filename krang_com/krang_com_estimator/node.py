"""com_estimator: learns beta from /balanced_pose and publishes it (thin shell over OnlineLearner).

Publishes ~/beta (latched, labelled), ~/com and ~/posterior (latched: beta and its covariance, for
the pose server's adaptive choice); serves ~/save (writes `output` atomically) and ~/reset."""

import sys
from dataclasses import dataclass, field
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from krang_model.beta import load_beta, save_beta
from krang_model.robot import load_krang
from krang_core import names, params
from krang_ros import messages, topics
from krang_ros.params import declare
from krang_ros.spin import run_node

from .registry import estimator_names
from .online import OnlineLearner, pitch_standard_error


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
        self.labels = self.robot.beta_labels()
        qos = topics.QOS
        self.beta_pub = self.create_publisher(
            Float64MultiArray, names.private(names.BETA), qos[names.BETA]
        )
        self.com_pub = self.create_publisher(
            PointStamped, names.private(names.COM), qos[names.COM]
        )
        self.posterior_pub = self.create_publisher(
            Float64MultiArray, names.private(names.POSTERIOR), topics.LATCHED
        )
        self.diag_pub = self.create_publisher(
            DiagnosticArray, names.relative(names.DIAGNOSTICS), qos[names.DIAGNOSTICS]
        )
        self.create_subscription(
            JointState,
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
        joints = messages.joints_from_state(msg, self.robot.pose_joints)
        pitch = messages.joints_from_state(msg, [names.BASE_PITCH])
        if joints is None or pitch is None:
            self.rejected += 1
            self.get_logger().error(
                f'rejected balanced pose: needs all body joints and {names.BASE_PITCH}, '
                f'finite (got {list(msg.name)})'
            )
            return
        try:
            beta = self.learner.add_balanced_pose(
                float(pitch[0]), joints, pitch_standard_error(msg)
            )
        except ValueError as err:
            self.rejected += 1
            self.get_logger().error(f'rejected balanced pose: {err}')
            return
        self.publish_beta()
        com = self.learner.com(float(pitch[0]), joints)
        point = PointStamped()
        point.header = msg.header
        point.header.frame_id = 'frame0'
        point.point.x, point.point.y, point.point.z = (float(v) for v in com)
        self.com_pub.publish(point)
        self.get_logger().info(
            f'pose {len(self.learner.poses)}: CoM x {1000 * com[0]:+.2f} mm at the measured '
            f'pitch; total mass {beta[0::4].sum():.2f} kg'
        )

    def publish_beta(self):
        self.beta_pub.publish(messages.labelled_array(self.learner.beta, self.labels))
        beta, cov = self.learner.posterior()
        n = len(beta)
        cov = np.zeros((n, n)) if cov is None else cov
        msg = Float64MultiArray()
        msg.layout.dim = [
            MultiArrayDimension(
                label='row 0 beta, rows 1.. covariance', size=n + 1, stride=(n + 1) * n
            ),
            MultiArrayDimension(label='beta entry', size=n, stride=n),
        ]
        msg.data = np.vstack([beta, cov]).ravel().tolist()
        self.posterior_pub.publish(msg)

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
            f'saved beta after {len(self.learner.poses)} poses to {path}',
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
                    'rejected': self.rejected,
                    'method': self.learner.method,
                },
            )
        )


def main(args=None):
    return run_node(ComEstimatorNode, args)


if __name__ == '__main__':
    sys.exit(main())
