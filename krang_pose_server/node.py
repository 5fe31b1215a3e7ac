"""pose_server: advances through the excitatory poses on /pose_server/next_pose (thin ROS shell)."""
import sys

import rclpy
from rclpy.node import Node
from std_srvs.srv import Trigger

from krang_model.config import config_path
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_ros import messages, topics

from .sequence import PoseSequence


class PoseServer(Node):
    def __init__(self):
        super().__init__('pose_server')
        self.robot = load_krang()
        poses_file = self.declare_parameter('poses_file', '').value or str(config_path('excitatory_poses.csv'))
        self.sequence = PoseSequence.from_csv(poses_file, self.robot, KRANG_POSE_COLUMNS)
        self.get_logger().info(f'{len(self.sequence)} poses from {poses_file}')
        self.cmd_pub = self.create_publisher(messages.JointState, topics.JOINT_POSITION_CMD,
                                             topics.QOS[topics.JOINT_POSITION_CMD])
        self.target_pub = self.create_publisher(messages.JointState, topics.POSE_TARGET, topics.QOS[topics.POSE_TARGET])
        self.diag_pub = self.create_publisher(messages.DiagnosticArray, topics.DIAGNOSTICS, topics.QOS[topics.DIAGNOSTICS])
        self.create_service(Trigger, '/pose_server/next_pose', self.on_next_pose)
        self.create_service(Trigger, '/pose_server/reset', self.on_reset)
        self.create_timer(1.0, self.publish_diagnostics)

    def on_next_pose(self, request, response):
        target = self.sequence.advance()
        if target is None:
            response.success = False
            response.message = f'no poses left (all {len(self.sequence)} done); call /pose_server/reset to start over'
            return response
        stamp = self.get_clock().now().to_msg()
        msg = messages.joint_state(stamp, self.robot.pose_joints, target.joints)
        self.cmd_pub.publish(msg)
        self.target_pub.publish(msg)
        response.success = True
        response.message = target.describe()
        self.get_logger().info(f'commanding {response.message}')
        return response

    def on_reset(self, request, response):
        self.sequence.reset()
        response.success = True
        response.message = f'back to the start of {len(self.sequence)} poses'
        self.get_logger().info(response.message)
        return response

    def publish_diagnostics(self):
        current = self.sequence.current()
        text = current.describe() if current else f'waiting for next_pose ({len(self.sequence)} poses)'
        self.diag_pub.publish(messages.diagnostics(self.get_clock().now().to_msg(), 'pose_server', 'ok', text,
                                                   {'cursor': self.sequence.cursor, 'total': len(self.sequence)}))


def main(args=None):
    rclpy.init(args=args)
    node = PoseServer()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
