"""The node set composed in one process (krang_cli/composed.py): what it rests on, and what it
gives. DDS must deliver a topic message between nodes of one process before `publish` returns, or
no step could know that everything it caused has been delivered; a service's answer comes back a
moment later (the session client waits for it with the physics held). Then two compositions with
the same seed must take the simulated robot through the same states, to the last bit, and another
seed must not."""

import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from conftest import next_ros_domain  # noqa: E402
from krang_cli.composed import ComposedSimulation  # noqa: E402
from krang_ros.spin import run_ready  # noqa: E402
from krang_sim.session_config import session_devices_file  # noqa: E402

PROFILES = {
    'reliable': QoSProfile(depth=10),
    'best effort': QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT),
    'latched': QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL),
}


@pytest.mark.parametrize('profile', sorted(PROFILES))
def test_dds_delivers_within_a_process_before_publish_returns(profile):
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        sender = rclpy.create_node('sender', context=context)
        receiver = rclpy.create_node('receiver', context=context)
        got = []
        qos = PROFILES[profile]
        pub = sender.create_publisher(Float64MultiArray, 'composed_probe', qos)
        receiver.create_subscription(
            Float64MultiArray, 'composed_probe', lambda m: got.append(m.data[0]), qos
        )
        receiver.create_service(Trigger, 'composed_probe_srv', lambda req, res: res)
        client = sender.create_client(Trigger, 'composed_probe_srv')
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(sender)
        executor.add_node(receiver)
        assert pub.get_subscription_count() == 1 and client.service_is_ready()
        for i in range(200):
            pub.publish(Float64MultiArray(data=[float(i)]))
            assert run_ready(executor) == 1
            assert got[-1] == i
        future = client.call_async(Trigger.Request())
        assert run_ready(executor) >= 1  # the request is served at once
        deadline = time.monotonic() + 5.0
        while not future.done() and time.monotonic() < deadline:
            run_ready(executor)  # the answer, a moment later
        assert future.done()
    finally:
        rclpy.try_shutdown(context=context)


def balance(tmp_path, seed, seconds=3.0):
    """A composition stands the robot up and balances `seconds` of simulated time; then the
    simulated time, the robot's state and the drives' currents. Each on a DDS domain of its own:
    a composition started right after another in the same process once found its controller's
    stand_up action never ready, the graph listing three servers of it, the two closed ones too
    (as `krang demo` does, one composition a process)."""
    next_ros_domain()
    devices = str(session_devices_file(tmp_path, virtual=True))
    composed = ComposedSimulation(
        {
            'sim_krang': {'devices_file': devices, 'seed': seed},
            'can_bridge': {'devices_file': devices},
        }
    )
    try:
        client = composed.session_client()
        client.enable_controller(timeout=60.0)
        client.wait_for_balance(timeout=60.0)
        client.pause(seconds)
        return (
            composed.sim_time,
            composed.sim.sim.state.copy(),
            composed.sim.devices.wheel_currents(),
        )
    finally:
        composed.close()


def test_same_seed_same_states_to_the_bit(tmp_path):
    t1, state1, currents1 = balance(tmp_path / 'a', seed=3)
    t2, state2, currents2 = balance(tmp_path / 'b', seed=3)
    t3, state3, _ = balance(tmp_path / 'c', seed=4)
    assert t1 == t2 and np.array_equal(state1, state2) and currents1 == currents2
    assert not np.array_equal(state1, state3)  # the noise matters: the check could fail


def test_the_bridge_reads_the_plants_joints_through_their_encoders(tmp_path):
    """The modules report the plant's joints as the sensor model's encoders read them (an encoder
    offset of the true robot included), not the modules' own motion profiles, which the plant
    follows."""
    next_ros_domain()
    devices = str(session_devices_file(tmp_path, virtual=True))
    composed = ComposedSimulation(
        {
            'sim_krang': {
                'devices_file': devices,
                'plant': 'mujoco',
                'effects': ['encoder_offset@JWaist=0.02'],
            },
            'can_bridge': {'devices_file': devices},
        }
    )
    try:
        client = composed.session_client()
        client.enable_controller(timeout=60.0)
        client.wait_for_balance(timeout=60.0)
        client.pause(0.5)
        sim = composed.sim
        with sim.lock:
            plant = dict(zip(sim.robot.pose_joints, sim.sim.joints))
            profile = sim.devices.joint_positions()
        js = composed.nodes['can_bridge'].core.joint_state()
        reported = dict(zip(js.names, js.positions))
        assert reported['JWaist'] == pytest.approx(plant['JWaist'] + 0.02, abs=1e-3)
        assert reported['JWaist'] == pytest.approx(profile['JWaist'] + 0.02, abs=1e-3)
        for joint in sim.robot.pose_joints:
            if joint != 'JWaist':
                assert reported[joint] == pytest.approx(plant[joint], abs=1e-3), joint
    finally:
        composed.close()
