"""state_publisher: robot_state_publisher's job for Krang (a shell over robot_frames.RobotFrames).

Publishes
- /robot_description (std_msgs/String, transient local): the URDF text (krang_model/krang.urdf);
- /tf (tf2_msgs/TFMessage): odom -> base_footprint -> base_link (REP-105: wheel odometry and the
  /imu/data orientation) and the moving joints from /joint_states, on each /joint_states message;
- /tf_static (transient local): the URDF's fixed joints, base_link -> Base first.
Subscribes /joint_states and /imu/data. Where tf2_msgs is not importable (this project's pip
environment has no tf2_msgs) /tf and /tf_static are not published: the node says so once in its
log and still publishes /robot_description. `krang view` uses the same core for Foxglove.
No parameters.
"""

import sys

from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import String

from krang_core import names
from krang_ros import topics
from krang_ros.robot_frames import WHEELS, RobotFrames
from krang_ros.spin import run_node

try:
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage
except ImportError:  # a pip environment without tf2_msgs: /tf is not published
    TFMessage = None

ROBOT_DESCRIPTION, TF, TF_STATIC = '/robot_description', '/tf', '/tf_static'


def transform_stamped(stamp, t):
    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id, msg.child_frame_id = t.parent, t.child
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in t.translation)
    rot.x, rot.y, rot.z, rot.w = t.quaternion
    return msg


def describe_parameters():
    """No parameters of its own: the URDF is the package's, the topics are remappable."""
    return []


class StatePublisherNode(Node):
    def __init__(self):
        super().__init__('state_publisher')
        self.frames = RobotFrames()
        self.imu_orientation = None
        description = self.create_publisher(String, ROBOT_DESCRIPTION, topics.LATCHED)
        description.publish(String(data=self.frames.urdf_text))
        qos = topics.QOS
        self.create_subscription(
            JointState,
            names.relative(names.JOINT_STATES),
            self.on_joint_states,
            qos[names.JOINT_STATES],
        )
        self.create_subscription(Imu, names.relative(names.IMU), self.on_imu, qos[names.IMU])
        if TFMessage is None:
            self.tf_pub = None
            self.get_logger().warning(
                'tf2_msgs is not importable (no ROS 2 tf2_msgs in this environment): /tf and '
                '/tf_static are NOT published; /robot_description is'
            )
            return
        self.tf_pub = self.create_publisher(TFMessage, TF, 100)
        static = self.create_publisher(TFMessage, TF_STATIC, topics.LATCHED)
        stamp = self.get_clock().now().to_msg()
        static.publish(
            TFMessage(
                transforms=[transform_stamped(stamp, t) for t in self.frames.static_transforms()]
            )
        )

    def on_imu(self, msg):
        q = msg.orientation
        self.imu_orientation = (q.x, q.y, q.z, q.w)

    def on_joint_states(self, msg):
        if self.tf_pub is None:
            return
        positions = dict(zip(msg.name, msg.position))
        self.frames.set_joints(positions)
        transforms = self.frames.joint_transforms(set(positions))
        if self.imu_orientation is not None and all(w in positions for w in WHEELS):
            transforms += self.frames.base_transforms(
                self.imu_orientation, *(positions[w] for w in WHEELS)
            )
        self.tf_pub.publish(
            TFMessage(transforms=[transform_stamped(msg.header.stamp, t) for t in transforms])
        )


def main(args=None):
    return run_node(StatePublisherNode, args)


if __name__ == '__main__':
    sys.exit(main())
