"""QoS of every topic of krang_core.names, defined once for every node, the recorder and the
tests."""

from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from krang_core import names

DEFAULT = QoSProfile(depth=10)
SENSOR = qos_profile_sensor_data
# A stream where only the newest message counts: after a stall the reader acts on the newest, never
# on a queue of older ones (a wheel current, a control sample), and no reliable bookkeeping is paid
# per message. rclpy's own /clock subscription (rclpy.time_source) uses this profile.
LATEST = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
# A sensor stream whose every sample a reader steps on (the controller's /imu/data): best effort,
# as SENSOR, so that any sensor-data publisher matches, but 50 deep: a reader stalled for up to 50
# samples (100 ms at 500 Hz) then takes them all in one wake and loses none. With SENSOR's 5 a
# 10 ms stall lost samples (bench_ros_latency.py --robot: 95.5-96.3 % of 500 Hz stepped); with 25,
# the controller found up to 25 waiting several hundred times in 20 s and stepped 98.2-98.8 %
# while the bridge published every sample; at 50, 99.8-100 %.
STEPPED = QoSProfile(depth=50, reliability=ReliabilityPolicy.BEST_EFFORT)
KEEP_ALL = QoSProfile(
    depth=1000, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE
)
LATCHED = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)

QOS = {
    names.JOINT_STATES: DEFAULT,
    names.IMU: SENSOR,
    names.WHEEL_EFFORT_CMD: LATEST,
    names.JOINT_POSITION_CMD: DEFAULT,
    names.BALANCED_POSE: KEEP_ALL,
    names.BETA: LATCHED,
    names.COM: DEFAULT,
    names.POSE_TARGET: LATCHED,
    names.STAND_ESTIMATE: LATCHED,
    names.DIAGNOSTICS: DEFAULT,
    names.CLOCK: LATEST,
    names.GROUND_TRUTH: DEFAULT,
}
