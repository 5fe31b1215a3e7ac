"""The ROS side of `krang view`: subscribes to the robot's topics and feeds
krang_ros.foxglove_view.LiveView, which serves them to Foxglove over a WebSocket.

Subscribes /joint_states, /imu/data, /com_estimator/beta (MassModel), /com_estimator/com,
/diagnostics (the controller's 'mode' value) and the latched /adrc_controller/mode
(ControllerMode) if a controller publishes one. Publishes nothing on ROS.
"""

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from krang_com_interfaces.msg import ControllerMode, MassModel
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState

from krang_core import names
from krang_core.message_values import mass_model_values, mode_name
from krang_ros import topics
from krang_ros.foxglove_view import LiveView


class LiveViewNode(Node):
    def __init__(self, port, host='127.0.0.1', rate_hz=20.0):
        super().__init__('krang_view')
        self.view = LiveView()
        self.port = self.view.start(port, host)
        qos = topics.QOS
        sub = self.create_subscription
        sub(
            JointState,
            names.relative(names.JOINT_STATES),
            self.on_joint_states,
            qos[names.JOINT_STATES],
        )
        sub(Imu, names.relative(names.IMU), self.on_imu, qos[names.IMU])
        sub(MassModel, names.BETA, self.on_beta, qos[names.BETA])
        sub(PointStamped, names.COM, self.on_com, qos[names.COM])
        sub(
            DiagnosticArray,
            names.relative(names.DIAGNOSTICS),
            self.on_diagnostics,
            qos[names.DIAGNOSTICS],
        )
        sub(
            ControllerMode,
            names.MODE,
            lambda msg: self.view.on_mode(mode_name(msg)),
            topics.LATCHED,
        )
        self.create_timer(1.0 / rate_hz, self.view.publish)
        self.create_timer(1.0, self.view.publish_scene)
        self.view.publish_scene()
        self.get_logger().info(
            f'Foxglove WebSocket server on ws://{host}:{self.port} '
            '(Foxglove: Open connection -> Foxglove WebSocket)'
        )

    def on_joint_states(self, msg):
        self.view.on_joints(dict(zip(msg.name, msg.position)))

    def on_imu(self, msg):
        q = msg.orientation
        self.view.on_imu((q.x, q.y, q.z, q.w))

    def on_beta(self, msg):
        model = mass_model_values(msg, self.view.robot.n_beta)
        if model is not None:
            self.view.on_beta(model[0])

    def on_com(self, msg):
        p = msg.point
        self.view.on_learned_com((p.x, p.y, p.z))

    def on_diagnostics(self, msg):
        for status in msg.status:
            for kv in status.values:
                if kv.key == 'mode':
                    self.view.on_mode(kv.value)

    def close(self):
        self.view.stop()
