"""The bare reference chain of `bench_ros_latency.py --robot`: the physical limit of rclpy here.

    can:   a frame 0x7E0 [counter] on a udp_multicast bus, received (python-can Notifier thread,
           as in can_bridge) and published as std_msgs/Float64MultiArray [counter], sensor QoS
           (as /imu/data); its subscription callback sends 0x7E1 [counter] back on the bus.
    relay: republishes each message from its subscription callback, reliable, depth 10.

The QoS is fixed (REF_QOS), not taken from ours: the reference stays the same chain
(nothing lost), whatever our topics use. The `can` end runs Python's switch interval at 0.5 ms,
as can_bridge does (it too has a receive thread beside its executor): both chains get the same
tuning, so that the ratio measures our work, not a setting.

Each runs in its own process on a SingleThreadedExecutor; the device player (device_player.py)
sends 0x7E0 and times the answer on the bus. The `can` end prints `answering` at its first answer.

    .venv/bin/python bench/ref_chain.py can --channel 239.74.163.99 --port 45000
    .venv/bin/python bench/ref_chain.py relay
"""

import argparse
import signal
import sys

import can
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

REF_REQUEST_ID, REF_ANSWER_ID = 0x7E0, 0x7E1
OUT, BACK = '/krang_bench/ref_sample', '/krang_bench/ref_command'
REF_QOS = {
    OUT: qos_profile_sensor_data,
    BACK: QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
}


class _Listener(can.Listener):
    def __init__(self, node):
        self.node = node

    def on_message_received(self, msg):
        self.node.on_frame(msg)


class CanEnd(Node):
    """Process 1: CAN in -> topic, topic -> CAN out."""

    def __init__(self, channel, port):
        super().__init__('bench_ref_can')
        self.bus = can.Bus(interface='udp_multicast', channel=channel, port=port)
        self.pub = self.create_publisher(Float64MultiArray, OUT, REF_QOS[OUT])
        self.create_subscription(Float64MultiArray, BACK, self.on_back, REF_QOS[BACK])
        self.notifier = can.Notifier(self.bus, [_Listener(self)], timeout=0.1)
        self.answering = False

    def on_frame(self, msg):
        if msg.arbitration_id == REF_REQUEST_ID and len(msg.data) == 4:
            self.pub.publish(Float64MultiArray(data=[float(int.from_bytes(msg.data, 'little'))]))

    def on_back(self, msg):
        counter = int(msg.data[0]) & 0xFFFFFFFF
        if not self.answering:
            self.answering = True
            print('answering', flush=True)  # the chain is up (bench_ros_latency.py waits for it)
        self.bus.send(
            can.Message(
                arbitration_id=REF_ANSWER_ID,
                is_extended_id=False,
                data=counter.to_bytes(4, 'little'),
            )
        )

    def close(self):
        self.notifier.stop()
        self.bus.shutdown()


class Relay(Node):
    """Process 2: republish from the subscription callback."""

    def __init__(self):
        super().__init__('bench_ref_relay')
        self.pub = self.create_publisher(Float64MultiArray, BACK, REF_QOS[BACK])
        self.create_subscription(Float64MultiArray, OUT, self.pub.publish, REF_QOS[OUT])

    def close(self):
        pass


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('role', choices=('can', 'relay'))
    p.add_argument('--channel', default='239.74.163.99')
    p.add_argument('--port', type=int, default=0)
    args = p.parse_args()
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    rclpy.init()
    if args.role == 'can':
        sys.setswitchinterval(0.0005)  # as can_bridge (module docstring)
    node = CanEnd(args.channel, args.port) if args.role == 'can' else Relay()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.close()
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
