"""What a control-path message costs as an rclpy message object and as its bytes (krang_ros.wire),
in one process over DDS: publish, and take with the fields the nodes read.

For `/imu/data` (sensor_msgs/Imu), `/joint_states` (a JointState of Krang's 19 joints with
positions, velocities and efforts) and the wheel command (a JointState of two efforts): the CPU
time of a publish of the message object (the reference, rclpy's own path) against a publish of
its bytes, and of a take of the object with its fields read against a take of the bytes read by
krang_ros.wire; each the best of --batches batches of --count messages, and the ratio. The
message is published, then taken back by a subscription of the same node.

    .venv/bin/python bench/bench_wire.py [--count 2000] [--batches 5]
"""

import argparse
import os
import time

import rclpy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState

from krang_model.robot import load_krang
from krang_core import names
from krang_ros import messages, topics, wire
from krang_ros.spin import take_latest


def messages_to_send():
    """(label, message type, bytes, the reader of the fields a node needs from an object, the
    wire reader)."""
    robot = load_krang()
    joints = list(robot.pose_joints) + list(names.WHEEL_JOINTS)
    n = len(joints)
    stamp = messages.stamp(1.5)
    imu = messages.imu(stamp, 'imu_link', -0.05, 1e-6, (0.0, 0.01, 0.0), (0.5, 0.0, 9.8))
    states = wire.joint_state_bytes(stamp, joints, [0.1] * n, [0.0] * n, [0.0] * n)
    command = messages.wheel_effort(stamp, names.WHEEL_JOINTS, (1.0, -1.0))

    def imu_fields(m):
        s = m.header.stamp
        o, w, a = m.orientation, m.angular_velocity, m.linear_acceleration
        return (s.sec, s.nanosec), (o.x, o.y, o.z, o.w), w.y, (a.x, a.y, a.z)

    def imu_wire(raw):
        s = wire.read_imu(raw)
        return s.stamp, s.orientation, s.angular_velocity[1], s.linear_acceleration

    def joint_fields(m):
        return messages.joints_from_state(m, robot.pose_joints)

    def joint_wire(raw):
        return messages.joints_from_state(wire.read_joint_state(raw), robot.pose_joints)

    def command_fields(m):
        return messages.wheel_efforts(m, names.WHEEL_JOINTS)

    def command_wire(raw):
        return messages.wheel_efforts(wire.read_joint_state(raw), names.WHEEL_JOINTS)

    return [
        ('/imu/data (Imu)', Imu, imu, imu_fields, imu_wire),
        (f'/joint_states ({n} joints)', JointState, states, joint_fields, joint_wire),
        ('wheel command (2 efforts)', JointState, command, command_fields, command_wire),
    ]


def best_us(step, count, batches):
    """The least CPU time of `step` per call, in us, over `batches` batches of `count` calls."""
    best = float('inf')
    for _ in range(batches):
        t0 = time.thread_time()
        for _ in range(count):
            step()
        best = min(best, (time.thread_time() - t0) / count)
    return best * 1e6


def measure(node, label, kind, raw, read_object, read_wire, count, batches):
    topic = 'bench_wire_' + str(abs(hash(label)))
    pub = node.create_publisher(kind, topic, topics.STEPPED)
    object_sub = node.create_subscription(kind, topic, lambda m: None, topics.STEPPED)
    raw_sub = node.create_subscription(kind, topic, lambda m: None, topics.STEPPED, raw=True)
    msg = deserialize_message(raw, kind)
    time.sleep(0.5)  # matched

    def taken(sub, read):
        def step():
            pub.publish(raw)
            got = None
            while got is None:
                got = take_latest(sub)
            read(got)

        return step

    figures = {
        'publish object': best_us(lambda: pub.publish(msg), count, batches),
        'publish bytes': best_us(lambda: pub.publish(raw), count, batches),
    }
    take_latest(object_sub), take_latest(raw_sub)
    figures['publish bytes + take bytes, read'] = best_us(
        taken(raw_sub, read_wire), count, batches
    )
    take_latest(object_sub)  # filled meanwhile: each message goes to both subscriptions
    figures['publish bytes + take object, read'] = best_us(
        taken(object_sub, read_object), count, batches
    )
    for sub in (object_sub, raw_sub):
        node.destroy_subscription(sub)
    node.destroy_publisher(pub)
    return figures


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--count', type=int, default=2000, help='messages per batch')
    p.add_argument('--batches', type=int, default=5, help='batches; the best is printed')
    args = p.parse_args()
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rclpy.init()
    node = rclpy.create_node('bench_wire')
    try:
        print(f'CPU per message, best of {args.batches} batches of {args.count} (us)')
        for label, kind, raw, read_object, read_wire in messages_to_send():
            f = measure(node, label, kind, raw, read_object, read_wire, args.count, args.batches)
            take_obj = f['publish bytes + take object, read'] - f['publish bytes']
            take_raw = f['publish bytes + take bytes, read'] - f['publish bytes']
            print(
                f'{label:30s} publish: object {f["publish object"]:6.1f}, bytes '
                f'{f["publish bytes"]:5.1f} ({f["publish object"] / f["publish bytes"]:.1f}x); '
                f'take and read: object {take_obj:6.1f}, bytes {take_raw:5.1f} '
                f'({take_obj / max(take_raw, 1e-9):.1f}x)'
            )
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
