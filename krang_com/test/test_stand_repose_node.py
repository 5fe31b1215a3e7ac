"""The re-pose after a stand-up caught back on its caster, over ROS: adrc_controller publishes each
catch's estimate once on its latched ~/stand_estimate, stamped as the step's mode change; while the
controller sits since that catch, pose_server moves the waist by the estimate to the pose
krang_pose_server.stand_pose.restand_pose gives, streamed without waiting for balance_converged,
and stops and holds where it is when the controller stands up meanwhile. An estimate that needs no
re-pose, one while the controller balances and one older than the sit move nothing. And the
chain in the simulated node set: a near-caster truth's stand-up caught, its waist re-posed."""

import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip('rclpy')
from krang_com_interfaces.msg import ControllerMode, StandEstimate  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Bool  # noqa: E402
from test_pose_server_node import NS, start_pose_server  # noqa: E402

from krang_adrc_controller.modes import ModesConfig  # noqa: E402
from krang_adrc_controller.node import AdrcControllerNode  # noqa: E402
from krang_cli.node_set import params_files  # noqa: E402
from krang_cli.processes import NodeSet  # noqa: E402
from krang_core import names  # noqa: E402
from krang_model.beta import save_beta  # noqa: E402
from krang_model.robot import load_krang  # noqa: E402
from krang_pose_server.stand_pose import restand_pose  # noqa: E402
from krang_ros import messages, topics  # noqa: E402
from krang_ros.session_client import open_session_client  # noqa: E402
from krang_sim.scenarios import stand_pose  # noqa: E402
from krang_sim.sensors import SensorNoise  # noqa: E402
from krang_sim.session_config import session_devices_file  # noqa: E402
from krang_sim.truths import TruthRecipe, generate_truth  # noqa: E402

ROBOT = load_krang()
#: the controller's default stand window, rad
WINDOW = (ModesConfig().stand_error_min_rad, ModesConfig().stand_error_max_rad)
#: the robot sits in the pose the nominal beta stands up from (the window's middle)
SITTING = stand_pose(ROBOT, ROBOT.nominal_beta)
#: the CoM-angle error estimates: the true CoM far forward (a re-pose), and behind (none needed)
FORWARD, BEHIND = -0.104, 0.05


class FakeController:
    """The controller's latched mode, stand_estimate and balance_converged (false) and the
    bridge's joint_states (the robot sitting in SITTING) beside a pose server, and what the pose
    server sends."""

    def __init__(self, node, context):
        self.node = node
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(node)
        self.commands, self.targets = [], []
        node.create_subscription(
            JointState, names.relative(names.JOINT_POSITION_CMD), self.commands.append, 100
        )
        node.create_subscription(
            JointState, f'{NS}/pose_server/target', self.targets.append, topics.LATCHED
        )
        self.mode_pub = node.create_publisher(
            ControllerMode, names.relative(names.MODE), topics.LATCHED
        )
        self.estimate_pub = node.create_publisher(
            StandEstimate,
            names.relative(names.STAND_ESTIMATE),
            topics.QOS[names.STAND_ESTIMATE],
        )
        self.joints_pub = node.create_publisher(
            JointState, names.relative(names.JOINT_STATES), topics.QOS[names.JOINT_STATES]
        )
        # sitting, the controller's balance estimate is not converged: a re-pose must not wait
        converged = node.create_publisher(
            Bool, names.relative(names.BALANCE_CONVERGED), topics.LATCHED
        )
        converged.publish(Bool(data=False))
        publishers = (self.mode_pub, self.estimate_pub, self.joints_pub, converged)
        self.spin_until(
            lambda: all(p.get_subscription_count() > 0 for p in publishers),
            30.0,
            'the pose server',
        )
        self.pause(0.5)  # joint_states in its reader

    def now(self):
        return self.node.get_clock().now().to_msg()

    def mode(self, name, stamp=None):
        self.mode_pub.publish(messages.controller_mode(stamp or self.now(), name))

    def estimate(self, error, tries=1, stamp=None):
        self.estimate_pub.publish(
            messages.stand_estimate(stamp or self.now(), tries, 3, error, WINDOW)
        )

    def spin_until(self, condition, timeout, what):
        """Spin (publishing joint_states at 20 Hz) until `condition()`."""
        end = time.monotonic() + timeout
        next_sample = 0.0
        while not condition():
            assert time.monotonic() < end, f'timed out waiting for {what}'
            if time.monotonic() >= next_sample:
                self.joints_pub.publish(
                    messages.joint_state(self.now(), ROBOT.pose_joints, SITTING)
                )
                next_sample = time.monotonic() + 0.05
            self.executor.spin_once(timeout_sec=0.02)

    def pause(self, seconds):
        end = time.monotonic() + seconds
        self.spin_until(lambda: time.monotonic() > end, seconds + 1.0, 'the time')


@pytest.fixture
def pose_server(tmp_path):
    yield from start_pose_server(tmp_path)


@pytest.fixture
def slow_pose_server(tmp_path):
    """Its moves limited to a balance-pitch rate of 0.02 rad/s: the re-pose takes seconds."""
    yield from start_pose_server(tmp_path, 'max_balance_rate_rad_s:=0.02')


def repose():
    """The pose a sitting robot is re-posed to after FORWARD, computed here."""
    pose = restand_pose(ROBOT, ROBOT.nominal_beta, SITTING, FORWARD, WINDOW)
    assert pose is not None and pose[0] < SITTING[0] - 0.05  # the waist back: the CoM back
    return pose


def test_a_caught_stand_up_re_poses_the_waist(pose_server):
    """The estimate arrives before the sit (two topics, no order between them): it waits for the
    sit of the same step and then streams the waist to restand_pose's pose."""
    _, node, context = pose_server
    fake = FakeController(node, context)
    pose = repose()
    caught = fake.now()  # the controller stamps the catch's mode change and estimate alike
    fake.mode('stand_up')
    fake.estimate(FORWARD, stamp=caught)
    fake.pause(0.5)
    assert not fake.commands, 'a re-pose while standing up'
    fake.mode('sit', stamp=caught)
    fake.spin_until(
        lambda: (
            fake.commands and np.allclose(fake.commands[-1].position, pose, rtol=0, atol=1e-12)
        ),
        20.0,
        'the re-pose to reach its pose',
    )
    np.testing.assert_allclose(fake.targets[-1].position, pose, rtol=0, atol=1e-12)
    sent = np.array([c.position for c in fake.commands])
    assert len(sent) >= 5, 'the waist jumped instead of moving'
    waist = sent[:, 0]
    assert SITTING[0] >= waist[0] and np.all(np.diff(waist) <= 0.0), waist
    np.testing.assert_allclose(sent[:, 1:], np.tile(SITTING[1:], (len(sent), 1)), atol=1e-12)
    fake.pause(0.5)
    assert len(fake.commands) == len(sent), 'commands after the re-pose ended'


def test_no_re_pose_when_none_is_needed_while_balancing_or_before_the_sit(pose_server):
    """An estimate whose CoM already lies far enough back, one while the controller balances,
    and that one still after a later sit (the robot balanced and sat down since the catch)."""
    _, node, context = pose_server
    fake = FakeController(node, context)
    fake.mode('sit')
    fake.estimate(BEHIND)
    fake.pause(1.0)
    fake.mode('balance')
    fake.estimate(FORWARD, tries=2)
    fake.pause(1.0)
    fake.mode('sit')
    fake.pause(1.0)
    assert not fake.commands and not fake.targets


def test_a_stand_up_stops_the_re_pose_where_it_is(slow_pose_server):
    _, node, context = slow_pose_server
    fake = FakeController(node, context)
    pose = repose()
    caught = fake.now()
    fake.mode('sit', stamp=caught)
    fake.estimate(FORWARD, stamp=caught)
    fake.spin_until(lambda: len(fake.commands) >= 5, 10.0, 'the re-pose')
    fake.mode('stand_up')  # the operator's stand_up
    fake.pause(0.5)  # the held setpoint's command
    n = len(fake.commands)
    fake.pause(1.0)
    assert len(fake.commands) == n, 'the re-pose went on while standing up'
    held = np.array(fake.commands[-1].position)
    np.testing.assert_array_equal(fake.targets[-1].position, held)  # the held pose: the target
    assert pose[0] < held[0] < SITTING[0], (pose[0], held[0])


def test_the_controller_publishes_each_catch_once_stamped_as_its_mode_change():
    """The controller node's publication, in this process, with the controller's estimate
    scripted: a new catch (its tries) is published once; None (BALANCE reached, or the tries
    granted again) publishes nothing, and the next catch's try 1 is new again."""
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = AdrcControllerNode(context=context)
        probe = Node('stand_estimate_probe', context=context)
        got, modes = [], []
        probe.create_subscription(
            StandEstimate, names.STAND_ESTIMATE, got.append, topics.QOS[names.STAND_ESTIMATE]
        )
        probe.create_subscription(ControllerMode, names.MODE, modes.append, topics.LATCHED)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(probe)
        script = [(1, -0.104), (1, -0.104), None, (1, -0.09), (2, -0.1), (2, -0.1)]
        expected = [1, 1, 1, 2, 3, 3]  # messages received after each step
        estimates = iter(script)
        node.controller.stand_estimate = lambda: next(estimates)
        end = time.monotonic() + 10.0
        while probe.count_publishers(names.STAND_ESTIMATE) == 0:
            assert time.monotonic() < end, 'the probe never saw the controller'
            executor.spin_once(timeout_sec=0.05)
        for n in expected:
            node.on_tick()  # no sensor data: a step towards safe_stop, the estimate scripted
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.02)
            assert len(got) == n, [(m.tries, m.com_angle_error) for m in got]
        assert [(m.tries, m.com_angle_error) for m in got] == [(1, -0.104), (1, -0.09), (2, -0.1)]
        modes_cfg = node.config.modes
        for m in got:
            assert m.tries_max == modes_cfg.stand_tries
            assert (m.stand_window_min, m.stand_window_max) == (
                modes_cfg.stand_error_min_rad,
                modes_cfg.stand_error_max_rad,
            )
        assert modes and got[0].header.stamp == modes[0].header.stamp  # the first step's change
        probe.destroy_node()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


#: a generated truth whose CoM at SITTING lies 0.6 mrad behind the axle on the caster
#: (test_stand_repose.py's nearest)
NEAR_CASTER_TRUTH = 8261


@pytest.mark.timeout(180)
def test_the_node_set_re_poses_a_caught_stand_up(tmp_path):
    """sim_krang with NEAR_CASTER_TRUTH sitting in SITTING, can_bridge, adrc_controller and
    pose_server, stood up by the operator's stand_up: the stand-up falls back and is caught, the
    controller publishes its estimate once, the pose server moves the waist back until the
    measured joints are where the controller's retry waits for them (within 0.01 rad of the
    target, its move_pending), and the retry stands up: the stand_up goal ends balancing."""
    truth = tmp_path / 'truth.yaml'
    save_beta(truth, generate_truth(ROBOT, NEAR_CASTER_TRUTH, TruthRecipe()).beta, ROBOT)
    devices = session_devices_file(tmp_path)
    logs = tmp_path / 'logs'
    nodes = NodeSet(params_files(sim=True), log_dir=logs)
    pose = '[' + ','.join(repr(float(v)) for v in SITTING) + ']'
    nodes.start('sim_krang', {'devices_file': devices, 'true_beta': truth, 'initial_pose': pose})
    nodes.start('can_bridge', {'devices_file': devices})
    nodes.start('adrc_controller')
    nodes.start('pose_server', {'selection': 'fixed'})
    client, context = open_session_client()
    try:
        estimates, targets, joints = [], [], [None]
        qos = topics.QOS
        client.create_subscription(
            StandEstimate, names.STAND_ESTIMATE, estimates.append, qos[names.STAND_ESTIMATE]
        )
        client.create_subscription(
            JointState, names.POSE_TARGET, targets.append, qos[names.POSE_TARGET]
        )
        client.create_subscription(
            JointState,
            names.JOINT_STATES,
            lambda m: joints.__setitem__(0, messages.joints_from_state(m, ROBOT.pose_joints)),
            qos[names.JOINT_STATES],
        )

        def arrived():
            return (
                targets
                and joints[0] is not None
                and np.all(np.abs(joints[0] - np.array(targets[-1].position)) <= 0.01)
            )

        client.enable_controller(timeout=60.0)  # and the operator's stand_up
        client.spin_until(
            lambda: (estimates and arrived()) or client.mode == 'safe_stop' or nodes.dead(),
            60.0,
            'the re-pose',
        )
        assert not nodes.dead(), f'nodes exited: {nodes.dead()} (logs in {logs})'
        assert 'sit' in client.modes[client.modes.index('stand_up') :], client.modes
        # the operator's one stand_up goes on: the retry stands up, and its goal succeeds
        client.wait_for_balance(60.0)
        assert client.modes.count('stand_up') == 2, client.modes
    finally:
        client.close()
        rclpy.try_shutdown(context=context)
        nodes.stop(('pose_server', 'adrc_controller', 'can_bridge', 'sim_krang'))
    assert [m.tries for m in estimates] == [1], estimates
    assert estimates[0].com_angle_error < -0.05, estimates[0]  # the true CoM lies forward
    assert len(targets) == 1, 'one move: the re-pose'
    moved = np.array(targets[0].position) - SITTING
    # the waist back (the CoM back), the other joints where they were measured (within the
    # simulated encoders' noise)
    assert moved[0] < -0.05 and np.all(np.abs(moved[1:]) < 6 * SensorNoise().joint_std_rad), moved
    with open(logs / 'pose_server.log') as log:
        assert any('re-posing the waist' in line for line in log)
