"""com_estimator over ROS: a BalancedPose in, a MassModel out with the posterior covariance, the
estimator's name and the count of poses, the same beta as the OnlineLearner offline (so a bag
replays to it); the learned pose's CoM in base_footprint; a pose without every joint is refused."""

import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PointStamped  # noqa: E402
from krang_com_interfaces.msg import BalancedPose, MassModel  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from krang_adrc_controller.detector import BalancedPoint  # noqa: E402
from krang_cli.relearn import REPRODUCTION_TOLERANCE  # noqa: E402
from krang_com_estimator.node import ComEstimatorNode  # noqa: E402
from krang_com_estimator.online import OnlineLearner  # noqa: E402
from krang_core import names  # noqa: E402
from krang_model import com  # noqa: E402
from krang_model.robot import load_krang  # noqa: E402
from krang_ros import messages, topics  # noqa: E402


class EstimatorPeer:
    """com_estimator and a peer node on one executor: the peer publishes /balanced_pose and
    collects ~/beta and ~/com."""

    def __init__(self, tmp_path):
        self.node = ComEstimatorNode(
            parameter_overrides=[Parameter('output', value=str(tmp_path / 'beta.yaml'))]
        )
        self.peer = rclpy.create_node('peer')
        self.models, self.points = [], []
        self.peer.create_subscription(
            MassModel, names.BETA, self.models.append, topics.QOS[names.BETA]
        )
        self.peer.create_subscription(
            PointStamped, names.COM, self.points.append, topics.QOS[names.COM]
        )
        self.pub = self.peer.create_publisher(
            BalancedPose, names.BALANCED_POSE, topics.QOS[names.BALANCED_POSE]
        )
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.executor.add_node(self.peer)
        self.spin_until(lambda: self.models and self.pub.get_subscription_count())

    def spin_until(self, condition, seconds=10.0):
        end = time.monotonic() + seconds
        while not condition() and time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.peer.destroy_node()


def test_a_balanced_pose_in_a_mass_model_out(tmp_path):
    robot = load_krang()
    joints = np.random.default_rng(11).uniform(robot.lower, robot.upper)
    truth = robot.nominal_beta.copy()
    truth[4 * robot.body_names.index('Spine') + 3] += 0.4  # the truth's Spine CoM moved
    q_base = float(com.balance_pitch(robot, joints[None], truth)[0])
    se = {'q_base_se': 4e-4, 'joints_se': np.full(len(joints), 1e-4)}
    point = BalancedPoint(3.0, q_base, joints, q_base_std=0.002, n_samples=100, window_s=2.0, **se)
    rclpy.init()
    try:
        est = EstimatorPeer(tmp_path)
        node, models, points = est.node, est.models, est.points
        incomplete = messages.balanced_pose(messages.stamp(2.0), robot.pose_joints[1:], point)
        incomplete.positions = incomplete.positions[1:]
        est.pub.publish(incomplete)
        est.pub.publish(messages.balanced_pose(messages.stamp(3.0), robot.pose_joints, point))
        est.spin_until(lambda: len(models) >= 2 and points)
        est.spin_until(lambda: False, 0.3)  # nothing more comes
        published = dict(node.get_publisher_names_and_types_by_node('com_estimator', '/'))
        est.close()
    finally:
        rclpy.try_shutdown()
    assert node.rejected == 1 and len(models) == 2 and len(points) == 1
    first, learned = models
    assert (first.poses, learned.poses) == (0, 1)
    assert first.source == learned.source == 'map-online'
    assert list(learned.body_names) == list(robot.body_names)
    # the offline learner's, to the digits `krang relearn` reproduces (krang_cli/relearn.py)
    offline = OnlineLearner(robot, robot.nominal_beta)
    close = {'rtol': 0.0, 'atol': REPRODUCTION_TOLERANCE * np.abs(robot.nominal_beta).max()}
    np.testing.assert_allclose(first.beta, offline.beta, **close)
    offline.add_balanced_pose(q_base, joints, 4e-4)
    beta, cov = offline.posterior()
    np.testing.assert_allclose(learned.beta, beta, **close)
    np.testing.assert_allclose(np.reshape(learned.covariance, cov.shape), cov, rtol=1e-9)
    assert len(first.covariance) == robot.n_beta**2
    (point_msg,) = points
    assert point_msg.header.frame_id == 'base_footprint'
    assert point_msg.header.stamp.sec == 3
    x, _, z = offline.com(q_base, joints)
    assert point_msg.point.x == pytest.approx(x, abs=1e-12)
    assert point_msg.point.z == pytest.approx(z + robot.wheel_radius, abs=1e-12)
    assert {t: v for t, v in published.items() if t.startswith('/com_estimator/')} == {
        names.BETA: ['krang_com_interfaces/msg/MassModel'],
        names.COM: ['geometry_msgs/msg/PointStamped'],
    }


def test_points_read_while_moving_go_out_with_the_next_poses_beta(tmp_path):
    """Two points read while moving (`in_motion`) are learned but publish nothing; the next point
    at rest publishes one beta, that of all three (the offline learner's), counted as one pose."""
    robot = load_krang()
    rng = np.random.default_rng(12)
    truth = robot.nominal_beta.copy()
    truth[4 * robot.body_names.index('Spine') + 1] += 0.3
    points = []
    for k, moving in enumerate((True, True, False)):
        joints = rng.uniform(robot.lower, robot.upper)
        q = float(com.balance_pitch(robot, joints[None], truth)[0])
        se = 1e-3 if moving else 3e-4
        points.append(BalancedPoint(1.0 + k, q, joints, 0.002, 100, 1.0, se, in_motion=moving))
    rclpy.init()
    try:
        est = EstimatorPeer(tmp_path)
        node, models = est.node, est.models
        for p in points[:2]:
            est.pub.publish(messages.balanced_pose(messages.stamp(p.t), robot.pose_joints, p))
        est.spin_until(lambda: node.learner.moving_points == 2)
        est.spin_until(lambda: False, 0.3)
        before_rest = len(models)
        est.pub.publish(messages.balanced_pose(messages.stamp(3.0), robot.pose_joints, points[2]))
        est.spin_until(lambda: len(models) >= 2)
        est.spin_until(lambda: False, 0.3)
        est.close()
    finally:
        rclpy.try_shutdown()
    assert before_rest == 1 and len(models) == 2
    assert models[1].poses == 1 and node.learner.moving_points == 2
    offline = OnlineLearner(robot, robot.nominal_beta)
    for p in points:
        offline.add_balanced_pose(p.q_base, p.joints, p.q_base_se)
    close = {'rtol': 0.0, 'atol': REPRODUCTION_TOLERANCE * np.abs(robot.nominal_beta).max()}
    np.testing.assert_allclose(models[1].beta, offline.beta, **close)
