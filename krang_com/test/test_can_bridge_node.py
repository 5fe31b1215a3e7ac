"""can_bridge node end to end: real rclpy, udp_multicast buses, the device emulators on the robot
side."""

import math
import random
import threading
import time

import can
import pytest
import yaml

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('msgpack')  # python-can's udp_multicast needs it

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402
from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from sensor_msgs.msg import Imu, JointState  # noqa: E402
from krang_com_interfaces.msg import DriveFault  # noqa: E402

from krang_can_bridge.config import load_devices  # noqa: E402
from krang_can_bridge.node import CanBridgeNode  # noqa: E402
from krang_model.drivetrain import drivetrain  # noqa: E402
from krang_model.robot import load_krang  # noqa: E402
from krang_core import names  # noqa: E402
from krang_ros import messages, topics, wire  # noqa: E402
from krang_sim.devices import KrangCanDevices  # noqa: E402


def wheel_command(efforts):
    """A /wheel_effort_cmd as the controller sends it (unstamped here)."""
    return messages.wheel_effort(Time(), names.WHEEL_JOINTS, efforts)


@pytest.fixture
def devices_file(tmp_path):
    """The shipped device map with private multicast groups, so parallel runs never share a bus."""
    base = load_devices()
    data = yaml.safe_load(base.path.read_text())
    rng = random.Random()
    group = f'239.74.{rng.randint(100, 250)}'
    for i, name in enumerate(data['buses']):
        data['buses'][name] = {
            'interface': 'udp_multicast',
            'channel': f'{group}.{i + 1}',
            'options': {'port': rng.randint(40000, 60000)},
        }
    data['dbc_file'] = str(base.dbc_path)
    path = tmp_path / 'can_devices.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


class Robot:
    """KrangCanDevices on udp_multicast buses with a 250 Hz loop (what sim_krang does around its
    physics)."""

    def __init__(self, cfg, q0):
        self.cfg = cfg
        self.devices = KrangCanDevices(cfg, initial_joint_positions=q0)
        self.lock = threading.Lock()
        self.buses = {b: can.Bus(**cfg.buses[b].bus_kwargs()) for b in cfg.buses_in_use()}
        self.notifiers = [
            can.Notifier(bus, [self._listener(name)], timeout=0.05)
            for name, bus in self.buses.items()
        ]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.loop, daemon=True)
        self.thread.start()

    def _listener(self, name):
        robot = self

        class L(can.Listener):
            def on_message_received(self, msg):
                with robot.lock:
                    replies = robot.devices.on_frame(name, msg)
                for r in replies:
                    robot.buses[r.bus].send(r.msg)

        return L()

    def loop(self, dt=0.004):
        while not self.stop.is_set():
            with self.lock:
                self.devices.step(dt)
                out = self.devices.wheel_feedback_frames(
                    {'JLWheel': 0.4, 'JRWheel': -0.6}, {'JLWheel': 0.0, 'JRWheel': 0.0}
                )
                out += self.devices.imu_frames_from_pitch(-1.2, 0.0)
            for f in out:
                self.buses[f.bus].send(f.msg)
            time.sleep(dt)

    def close(self):
        self.stop.set()
        self.thread.join(2.0)
        for n in self.notifiers:
            n.stop()
        for b in self.buses.values():
            b.shutdown()


@pytest.mark.timeout(60)
def test_node_bridges_states_and_commands(devices_file):
    cfg = load_devices(devices_file)
    robot = Robot(cfg, {'JWaist': 1.5, 'LJ4': -0.8})
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    bridge = CanBridgeNode(
        context=ctx, parameter_overrides=[Parameter('devices_file', value=str(devices_file))]
    )
    probe = rclpy.create_node('probe', context=ctx)
    got = {}
    probe.create_subscription(JointState, '/joint_states', lambda m: got.__setitem__('js', m), 10)
    probe.create_subscription(
        Imu, '/imu/data', lambda m: got.__setitem__('imu', m), qos_profile_sensor_data
    )
    probe.create_subscription(
        DiagnosticArray, '/diagnostics', lambda m: got.__setitem__('diag', m), 10
    )
    probe.create_subscription(
        DriveFault, names.DRIVE_FAULT, lambda m: got.__setitem__('fault', m), topics.LATCHED
    )
    effort_pub = probe.create_publisher(
        JointState,
        '/wheel_effort_cmd',
        QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
    )
    joint_pub = probe.create_publisher(JointState, '/joint_position_cmd', 10)
    ex.add_node(bridge)
    ex.add_node(probe)
    # the receive thread serves the DMU's bus first (test_can_bus_io.py: in the order given)
    assert next(iter(bridge.runtime.reader._by_fd.values()))[0] == cfg.imu.bus

    def spin_until(cond, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end and not cond():
            ex.spin_once(timeout_sec=0.02)
        return cond()

    def joints():
        js = got.get('js')
        return dict(zip(js.name, js.position)) if js else {}

    try:
        # the modules answer polls one by one: wait until every joint has been reported once
        assert spin_until(
            lambda: all(j in joints() for j in ('JLWheel', 'JRWheel', 'JWaist', 'LJ4')), 10.0
        ), joints()
        assert joints()['JLWheel'] == pytest.approx(0.4, abs=1e-3)
        assert joints()['JRWheel'] == pytest.approx(-0.6, abs=1e-3)
        assert joints()['JWaist'] == pytest.approx(1.5, abs=1e-5)
        assert joints()['LJ4'] == pytest.approx(-0.8, abs=1e-5)
        assert spin_until(lambda: 'imu' in got, 5.0)
        q = got['imu'].orientation
        assert 2 * math.atan2(q.y, q.w) == pytest.approx(-1.2, abs=5e-3)

        def motion_ok():
            d = got.get('diag')
            return d is not None and any(
                s.name == 'can_bridge: motion' and s.level == b'\x00' for s in d.status
            )

        assert spin_until(motion_ok, 10.0), [(s.name, s.message) for s in got['diag'].status][:3]

        drive = drivetrain(load_krang())
        expected = 8.0 / (drive.torque_constant * drive.gear_ratio)

        def current_arrived():
            effort_pub.publish(wheel_command([8.0, 8.0]))
            c = robot.devices.wheel_currents()
            return abs(c['JLWheel'] - expected) < 0.01 and abs(c['JRWheel'] - expected) < 0.01

        assert spin_until(current_arrived, 5.0), robot.devices.wheel_currents()
        # latched clear from the start: no fault
        assert not got['fault'].active and got['fault'].reason == ''

        # half-invalid: both wheels stop, and /diagnostics WARNs with the count and the reason
        def both_zero_and_warned():
            effort_pub.publish(wheel_command([math.nan, 20.0]))
            d = got.get('diag')
            warned = d is not None and any(
                s.name == 'can_bridge: commands' and s.level == b'\x01' and 'JLWheel' in s.message
                for s in d.status
            )
            return warned and robot.devices.wheel_currents() == {'JLWheel': 0.0, 'JRWheel': 0.0}

        assert spin_until(both_zero_and_warned, 5.0), robot.devices.wheel_currents()
        assert spin_until(current_arrived, 5.0), robot.devices.wheel_currents()

        # bytes that are not a JointState (a command cut short): both wheels stop as well
        def cut_short_stops_both():
            effort_pub.publish(wheel_command([8.0, 8.0])[:40])
            return robot.devices.wheel_currents() == {'JLWheel': 0.0, 'JRWheel': 0.0}

        assert spin_until(cut_short_stops_both, 5.0), robot.devices.wheel_currents()
        assert spin_until(current_arrived, 5.0), robot.devices.wheel_currents()

        # streamed, as the pose server does: a setpoint that arrives while a device is briefly
        # silent (a 50 ms stall of this process's emulator thread on a loaded CI machine) is
        # dropped by design, and the next one moves the joint
        def torso_at_target():
            joint_pub.publish(JointState(name=['JTorso'], position=[0.1]))
            return abs(joints().get('JTorso', 0.0) - 0.1) < 1e-3

        assert spin_until(torso_at_target, 5.0), joints().get('JTorso')

        # the controller stops publishing: the wheel command goes stale -> zero current
        assert spin_until(
            lambda: robot.devices.wheel_currents() == {'JLWheel': 0.0, 'JRWheel': 0.0}, 2.0
        )
    finally:
        bridge.close()
        ex.shutdown()
        bridge.destroy_node()
        probe.destroy_node()
        rclpy.shutdown(context=ctx)
        robot.close()


@pytest.mark.timeout(60)
def test_wheel_sample_goes_out_just_before_the_next_imu_sample(tmp_path):
    """While the DMU streams, a complete wheel sample's /joint_states waits for the next DMU
    sample and is published just before its /imu/data: the wheel work never lands between a
    sample and its command (README, "Where a sample's time goes"), and the controller's step on
    a sample always has the newest wheel sample before it. Once the DMU stops, each wheel sample
    goes out at once. Frames are handed over by a Pump, so the order is exact."""
    from krang_can_bridge.bus_io import Pump
    from krang_sim.session_config import session_devices_file

    cfg = load_devices(session_devices_file(tmp_path, virtual=True))
    robot = KrangCanDevices(cfg, auto_enable_wheels=True)
    device_buses = {b: can.Bus(**cfg.buses[b].bus_kwargs()) for b in cfg.buses_in_use()}
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    pump = Pump()
    bridge = CanBridgeNode(
        context=ctx,
        pump=pump,
        parameter_overrides=[
            Parameter('devices_file', value=str(cfg.path)),
            Parameter('amc_startup', value=False),
            Parameter('publish_rate_hz', value=0.0),
        ],
    )
    published = []  # (topic, wheel position or pitch rate) in the order published
    for pub, topic in ((bridge.joint_pub, 'joints'), (bridge.imu_pub, 'imu')):

        def record(raw, publish=pub.publish, topic=topic):
            if topic == 'joints':
                msg = wire.read_joint_state(raw)
                published.append((topic, dict(zip(msg.name, msg.position)).get('JLWheel')))
            else:
                published.append((topic, wire.read_imu(raw).angular_velocity[1]))
            publish(raw)

        pub.publish = record

    def send(frames):
        for f in frames:
            device_buses[f.bus].send(f.msg)
        pump.pump()

    def wheels(position):
        send(
            robot.wheel_feedback_frames(
                {j: position for j in robot.wheels}, dict.fromkeys(robot.wheels, 0.0)
            )
        )

    def dmu():
        send(robot.imu_frames_from_pitch(-1.2, 0.0))

    # a 25 Hz DMU (held below 20 Hz: IMU_HOLD_MAX_S): a wheel sample 0.3 periods after a DMU
    # sample is held unless this process stalls 48 ms in between
    period = 0.04
    try:
        for _ in range(200):  # until the IMU filter publishes (and its interval is known)
            dmu()
            time.sleep(period)
            if sum(topic == 'imu' for topic, _ in published) >= 2:
                break
        assert [t for t, _ in published].count('imu') >= 2, published
        published.clear()
        dmu()
        time.sleep(0.3 * period)
        wheels(0.1)
        assert [t for t, _ in published] == ['imu'], 'a wheel sample went out between samples'
        time.sleep(0.7 * period)
        dmu()
        assert [t for t, _ in published[1:]] == ['joints', 'imu'], published
        assert published[1][1] == pytest.approx(0.1, abs=1e-3)
        # two wheel samples before one DMU sample: only the newer goes out
        time.sleep(0.3 * period)
        wheels(0.2)
        wheels(0.3)
        time.sleep(0.7 * period)
        dmu()
        assert [t for t, _ in published[3:]] == ['joints', 'imu'], published
        assert published[3][1] == pytest.approx(0.3, abs=1e-3)
        # the DMU stops: after 1.5 of its periods each wheel sample goes out at once
        published.clear()
        time.sleep(2.0 * period)
        wheels(0.4)
        wheels(0.5)
        assert published == [
            ('joints', pytest.approx(0.4, abs=1e-3)),
            ('joints', pytest.approx(0.5, abs=1e-3)),
        ]
    finally:
        bridge.close()
        bridge.destroy_node()
        rclpy.shutdown(context=ctx)
        for bus in device_buses.values():
            bus.shutdown()
