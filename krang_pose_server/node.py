"""pose_server: advances through the excitatory poses on /pose_server/next_pose (thin ROS
shell)."""
import sys

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from krang_model.config import config_path
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_ros import messages, names, topics
from krang_ros.spin import run_node

from .sequence import PoseSequence, StraightLineMove


class PoseServer(Node):
    def __init__(self):
        super().__init__('pose_server')
        self.robot = load_krang()
        poses_file = (self.declare_parameter('poses_file', '').value
                      or str(config_path('excitatory_poses.csv')))
        self.sequence = PoseSequence.from_csv(poses_file, self.robot, KRANG_POSE_COLUMNS)
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
        self.stream_rate = self.declare_parameter('stream_rate_hz', 20.0).value
        self.speed_fraction = self.declare_parameter('speed_fraction', 0.8).value
        self.measured = None
        self.move = None
        self.move_started = None
        self.create_timer(1.0 / self.stream_rate, self.stream_move)
        self.create_timer(1.0, self.publish_diagnostics)

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
        target = self.sequence.advance()
        if target is None:
            response.success = False
            response.message = (f'no poses left (all {len(self.sequence)} done); call '
                                f'{names.POSE_RESET} to start over')
            return response
        if self.measured is not None:
            start = self.measured
        else:
            start = self.move.goal if self.move else target.joints
        self.move = StraightLineMove.plan(start, target.joints, self.robot.velocity_limit,
                                          self.speed_fraction)
        self.move_started = self.now()
        self.target_pub.publish(messages.joint_state(self.get_clock().now().to_msg(),
                                                     self.robot.pose_joints, target.joints))
        self.stream_move()
        response.success = True
        response.message = f'{target.describe()} (moving for {self.move.duration:.1f} s)'
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
        if current:
            text = current.describe()
        else:
            text = f'waiting for next_pose ({len(self.sequence)} poses)'
        self.diag_pub.publish(messages.diagnostics(
            self.get_clock().now().to_msg(), 'pose_server', 'ok', text,
            {'cursor': self.sequence.cursor, 'total': len(self.sequence)}))


def main(args=None):
    return run_node(PoseServer, args)


if __name__ == '__main__':
    sys.exit(main())
