"""state_publisher: robot_state_publisher's job for Krang (a shell over robot_frames.RobotFrames),
and the CoM as `krang view` draws it, so that a bag of the node set opens in Foxglove with the
robot posed and its CoM shown.

Publishes
- /robot_description (std_msgs/String, transient local): the URDF text (krang_model/krang.urdf);
- /tf (tf2_msgs/TFMessage): odom -> base_footprint -> base_link (REP-105: wheel odometry and the
  /imu/data orientation) and the moving joints from /joint_states, at most `publish_frequency`
  times per second of the /joint_states stamps, stamped as the /joint_states message;
- /tf_static (transient local): the URDF's fixed joints, base_link -> Base first;
- /state_publisher/com (visualization_msgs/MarkerArray) with each /tf: the CoM of the latest
  /com_estimator/beta (the URDF's nominal beta before one arrives) at the measured pitch and
  joints, in base_footprint (robot_frames.com_marks).
Subscribes /joint_states, /imu/data and /com_estimator/beta. Where tf2_msgs is not importable /tf,
/tf_static and the CoM are not published: the node says so once in its log and still publishes
/robot_description. `krang view` uses the same core for Foxglove.
"""

import sys
from dataclasses import dataclass, field

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from krang_com_interfaces.msg import MassModel
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import ColorRGBA, String
from visualization_msgs.msg import Marker, MarkerArray

from krang_core import names, params
from krang_core.message_values import mass_model_values
from krang_model.robot import load_krang
from krang_ros import topics, wire
from krang_ros.params import declare
from krang_ros.robot_frames import BASE_FOOTPRINT, WHEELS, RobotFrames, com_marks, com_now
from krang_ros.spin import run_node

try:
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage
except ImportError:  # an environment without tf2_msgs: /tf is not published
    TFMessage = None

ROBOT_DESCRIPTION, TF, TF_STATIC = '/robot_description', '/tf', '/tf_static'
COM_MARKERS = '/state_publisher/com'


@dataclass(frozen=True)
class StatePublisherParams:
    """state_publisher's parameters (read at start)."""

    publish_frequency: float = field(
        default=20.0,
        metadata={
            'doc': 'most /tf publications per second of /joint_states time, as '
            "robot_state_publisher's parameter of this name (0: one per /joint_states message)"
        },
    )

    def __post_init__(self):
        if not self.publish_frequency >= 0:
            raise ValueError(f'publish_frequency must be >= 0, got {self.publish_frequency}')


def describe_parameters():
    return params.describe(StatePublisherParams)


def transform_stamped(stamp, t, msg=None):
    """A robot_frames.Transform as a TransformStamped (filled into `msg` when given: building one
    costs more than filling it)."""
    msg = TransformStamped() if msg is None else msg
    msg.header.stamp = stamp
    msg.header.frame_id, msg.child_frame_id = t.parent, t.child
    tr, rot = msg.transform.translation, msg.transform.rotation
    tr.x, tr.y, tr.z = (float(v) for v in t.translation)
    rot.x, rot.y, rot.z, rot.w = t.quaternion
    return msg


def _set(point, p):
    point.x, point.y, point.z = (float(v) for v in p)


class ComMarkers:
    """robot_frames.ComMarks as visualization_msgs markers in base_footprint (namespace 'com'),
    in the colours and sizes of `krang view`'s CoM scene: two lines (the vertical through the
    axle, the axle to the CoM), two spheres (estimated, nominal) and the label. Built once, then
    filled at each update (a Marker costs more to build than to fill)."""

    def __init__(self):
        red, grey, green = (0.9, 0.15, 0.1, 1.0), (0.6, 0.6, 0.6, 0.7), (0.1, 0.8, 0.2, 1.0)
        kinds = (
            (Marker.LINE_STRIP, green, (0.01, 0.0, 0.0)),
            (Marker.LINE_STRIP, red, (0.008, 0.0, 0.0)),
            (Marker.SPHERE, red, (0.07, 0.07, 0.07)),
            (Marker.SPHERE, grey, (0.05, 0.05, 0.05)),
            (Marker.TEXT_VIEW_FACING, (1.0, 1.0, 1.0, 1.0), (0.0, 0.0, 0.04)),
        )
        self.array = MarkerArray()
        for k, (kind, rgba, scale) in enumerate(kinds):
            msg = Marker(type=kind, action=Marker.ADD, ns='com', id=k)
            msg.header.frame_id = BASE_FOOTPRINT
            msg.pose.orientation.w = 1.0
            msg.scale.x, msg.scale.y, msg.scale.z = scale
            msg.color = ColorRGBA(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
            if kind == Marker.LINE_STRIP:
                msg.points = [Point(), Point()]
            self.array.markers.append(msg)

    def update(self, stamp, marks):
        """The markers of `marks` (robot_frames.com_marks), stamped `stamp`."""
        vertical, arm, estimated, nominal, label = self.array.markers
        for msg in self.array.markers:
            msg.header.stamp = stamp
        for line, end in ((vertical, marks.top), (arm, marks.estimated)):
            _set(line.points[0], marks.axle)
            _set(line.points[1], end)
        _set(estimated.pose.position, marks.estimated)
        _set(nominal.pose.position, marks.nominal)
        _set(label.pose.position, marks.estimated + [0.0, 0.0, 0.12])
        label.text = marks.label
        return self.array


class StatePublisherNode(Node):
    def __init__(self, **kwargs):
        super().__init__('state_publisher', **kwargs)
        cfg = declare(self, StatePublisherParams)
        self.period_ns = int(1e9 / cfg.publish_frequency) if cfg.publish_frequency else 0
        self.last_ns = None
        self.frames = RobotFrames()
        self.robot = load_krang()
        self.beta = self.robot.nominal_beta
        self.imu_orientation = None
        description = self.create_publisher(String, ROBOT_DESCRIPTION, topics.LATCHED)
        description.publish(String(data=self.frames.urdf_text))
        qos = topics.QOS
        # as bytes (krang_ros.wire): a hundred samples a second of each, most of them not published
        self.create_subscription(
            JointState,
            names.relative(names.JOINT_STATES),
            self.on_joint_states,
            qos[names.JOINT_STATES],
            raw=True,
        )
        self.create_subscription(
            Imu, names.relative(names.IMU), self.on_imu, qos[names.IMU], raw=True
        )
        self.create_subscription(
            MassModel, names.relative(names.BETA), self.on_beta, qos[names.BETA]
        )
        if TFMessage is None:
            self.tf_pub = None
            self.get_logger().warning(
                'tf2_msgs is not importable (no ROS 2 tf2_msgs in this environment): /tf, '
                '/tf_static and the CoM are NOT published; /robot_description is'
            )
            return
        self.tf_pub = self.create_publisher(TFMessage, TF, 100)
        self.com_pub = self.create_publisher(MarkerArray, COM_MARKERS, 10)
        self.com_markers = ComMarkers()
        self.transforms = {}  # (parent, child) -> its TransformStamped, filled at each update
        static = self.create_publisher(TFMessage, TF_STATIC, topics.LATCHED)
        stamp = self.get_clock().now().to_msg()
        static.publish(
            TFMessage(
                transforms=[transform_stamped(stamp, t) for t in self.frames.static_transforms()]
            )
        )

    def on_imu(self, raw):
        try:
            self.imu_orientation = wire.read_imu(raw).orientation
        except wire.WireError:
            pass  # not an Imu: nothing to pose the base with

    def on_beta(self, msg):
        model = mass_model_values(msg, self.robot.n_beta)
        if model is not None:
            self.beta = model[0]

    def due(self, stamp):
        """Whether the /joint_states sample of this stamp is published (publish_frequency)."""
        t_ns = stamp.sec * 1_000_000_000 + stamp.nanosec
        if self.last_ns is not None and 0 <= t_ns - self.last_ns < self.period_ns:
            return False
        self.last_ns = t_ns
        return True

    def on_joint_states(self, raw):
        # the odometry integrates between the published samples: its travel is the wheels'
        # whole turn since the last one, whatever the rate
        try:
            msg = wire.read_joint_state(raw)
        except wire.WireError:
            return
        if self.tf_pub is None or not self.due(msg.stamp):
            return
        stamp = Time(sec=msg.stamp.sec, nanosec=msg.stamp.nanosec)
        positions = dict(zip(msg.name, msg.position))
        self.frames.set_joints(positions)
        transforms = self.frames.joint_transforms(set(positions))
        if self.imu_orientation is not None and all(w in positions for w in WHEELS):
            transforms += self.frames.base_transforms(
                self.imu_orientation, *(positions[w] for w in WHEELS)
            )
        self.tf_pub.publish(TFMessage(transforms=[self.transform(stamp, t) for t in transforms]))
        joints = [positions.get(j) for j in self.robot.pose_joints]
        if self.imu_orientation is not None and None not in joints:
            now = com_now(self.robot, self.frames, self.imu_orientation, joints, self.beta)
            marks = com_marks(*now, self.frames.radius)
            self.com_pub.publish(self.com_markers.update(stamp, marks))

    def transform(self, stamp, t):
        key = t.parent, t.child
        self.transforms[key] = transform_stamped(stamp, t, self.transforms.get(key))
        return self.transforms[key]


def main(args=None):
    return run_node(StatePublisherNode, args)


if __name__ == '__main__':
    sys.exit(main())
