"""QoS of every topic of krang_ros.names, defined once for every node, the recorder and the
tests."""

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

# Re-exported only for krang_adrc_controller/node.py, which still spells names as topics.X.
from .names import (
    BALANCED_POSE,
    BETA,
    CLOCK,
    COM,
    DIAGNOSTICS,
    GROUND_TRUTH,  # noqa: F401
    IMU,
    JOINT_POSITION_CMD,
    JOINT_STATES,
    POSE_TARGET,
    WHEEL_EFFORT_CMD,
)

DEFAULT = QoSProfile(depth=10)
SENSOR = qos_profile_sensor_data
COMMAND = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
KEEP_ALL = QoSProfile(
    depth=1000, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE
)
LATCHED = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)

QOS = {
    JOINT_STATES: DEFAULT,
    IMU: SENSOR,
    WHEEL_EFFORT_CMD: COMMAND,
    JOINT_POSITION_CMD: DEFAULT,
    BALANCED_POSE: KEEP_ALL,
    BETA: LATCHED,
    COM: DEFAULT,
    POSE_TARGET: LATCHED,
    DIAGNOSTICS: DEFAULT,
    CLOCK: DEFAULT,
    GROUND_TRUTH: DEFAULT,
}
