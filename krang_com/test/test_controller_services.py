"""The controller's operator controls over real processes (sim_krang, can_bridge, adrc_controller):
enable sits powered without standing; the stand_up action gives feedback and balances, and
cancelled it sits the robot back down; a stand-up while balancing is refused with the reason; the
sit_down action puts the robot back on its caster without a fall and cannot be cancelled; halt
zeroes the current, recover is refused while the bridge reports a drive fault; and the
controller's names move with its namespace (README, "Running on the robot")."""

import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('msgpack')  # python-can's udp_multicast needs it

from action_msgs.msg import GoalStatus  # noqa: E402
from krang_com_interfaces.msg import ControllerMode, DriveFault  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.action import get_action_names_and_types  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from std_srvs.srv import SetBool  # noqa: E402

from krang_cli.node_set import params_files  # noqa: E402
from krang_cli.processes import NodeSet  # noqa: E402
from krang_model.drivetrain import drivetrain  # noqa: E402
from krang_model.robot import load_krang  # noqa: E402
from krang_core import names  # noqa: E402
from krang_ros import messages, topics  # noqa: E402
from krang_ros.session_client import SessionError, open_session_client  # noqa: E402
from krang_sim.node import GROUND_TRUTH_FIELDS  # noqa: E402
from krang_sim.session_config import session_devices_file  # noqa: E402

NODES = ('sim_krang', 'can_bridge', 'adrc_controller')
#: |true pitch rate| bound while sitting down, rad/s (from the 10 Hz ground truth). Offline from
#: this pose: 0.37 rad/s with modes.sit_rate_rad_s 0.2; the hardware's step 0.80, a torque-free
#: fall (halt) 0.74.
SIT_RATE_MAX = 0.5
CASTER_TOL_RAD = 0.03  # sitting: the true pitch this close to the caster's contact pitch
SITTING_CURRENT_A = 1.0  # sitting still under the ground PD: |current| below this


class Watch:
    """The simulator's ground truth, as the test's node receives it."""

    def __init__(self, client):
        self.truth = []
        client.create_subscription(Float64MultiArray, names.GROUND_TRUTH, self.on_truth, 50)

    def on_truth(self, msg):
        self.truth.append(dict(zip(GROUND_TRUTH_FIELDS, msg.data)))


def wait_mode(client, mode, timeout):
    client.spin_until(lambda: client.mode == mode, timeout, f'mode {mode}')


def fault(client, reason):
    return messages.drive_fault(client.get_clock().now().to_msg(), reason)


@pytest.mark.timeout(300)
def test_operator_services_over_ros(tmp_path):
    caster = drivetrain(load_krang()).caster_pitch
    devices = session_devices_file(tmp_path)
    nodes = NodeSet(params_files(sim=True, extra=()), log_dir=tmp_path / 'logs')
    nodes.start('sim_krang', {'devices_file': devices})
    nodes.start('can_bridge', {'devices_file': devices})
    nodes.start('adrc_controller')
    client, context = open_session_client()
    try:
        watch = Watch(client)
        fault_pub = client.create_publisher(DriveFault, names.DRIVE_FAULT, topics.LATCHED)
        enable = client.enable
        for _ in range(300):  # refused until the sensor data flow
            try:
                if client.call(enable, SetBool.Request(data=True), timeout=5.0).success:
                    break
            except SessionError:  # a lost first answer (SessionClient.enable_controller): retry
                continue
            client.pause(0.2)
        wait_mode(client, 'sit', 10.0)
        client.pause(3.0)
        assert client.mode == 'sit', 'enable must not stand the robot up'

        goal = client.stand_up()  # cancelled while standing up: back onto the caster
        client.spin_until(
            lambda: client.mode == 'stand_up' and goal.feedback, 20.0, 'stand-up feedback'
        )
        assert client.cancel(goal)
        result = client.result(goal, 30.0)
        assert goal.status == GoalStatus.STATUS_CANCELED and not result.success, result.message
        assert 'sat back down' in result.message and result.mode == ControllerMode.SIT
        wait_mode(client, 'sit', 5.0)  # another topic than the result's: it can come after it
        assert client.modes[-3:] == ['stand_up', 'sit_down', 'sit'], client.modes
        client.pause(2.0)

        goal = client.stand_up()
        result = client.result(goal, 120.0)
        assert goal.status == GoalStatus.STATUS_SUCCEEDED and result.success, result.message
        assert result.mode == ControllerMode.BALANCE
        wait_mode(client, 'balance', 5.0)
        modes = [f.mode for f in goal.feedback]
        assert ControllerMode.STAND_UP in modes and set(modes) <= {0, 1, 2}, modes
        elapsed = [f.elapsed for f in goal.feedback]
        assert elapsed == sorted(elapsed) and elapsed[-1] > 1.0, elapsed
        assert all(caster - 0.1 < f.base_pitch < 0.0 for f in goal.feedback)
        assert caster + 0.1 < result.base_pitch < 0.0, result.base_pitch

        reply = client.call(enable, SetBool.Request(data=False))
        assert not reply.success and 'use sit_down or halt' in reply.message
        goal = client.stand_up()  # refused, with the reason
        result = client.result(goal, 10.0)
        assert goal.status == GoalStatus.STATUS_ABORTED and not result.success
        assert 'already balancing' in result.message, result.message
        client.pause(3.0)

        n_truth = len(watch.truth)
        goal = client.sit_down()
        assert not client.cancel(goal), 'a sit-down, once begun, ends on the caster'
        result = client.result(goal, 20.0)
        assert goal.status == GoalStatus.STATUS_SUCCEEDED and result.success, result.message
        assert result.mode == ControllerMode.SIT
        wait_mode(client, 'sit', 5.0)
        assert {f.mode for f in goal.feedback} <= {2, 3}
        client.pause(3.0)
        sat = watch.truth[n_truth:]
        rates = np.abs(np.diff([r['q_base'] for r in sat]) / np.diff([r['t'] for r in sat]))
        assert rates.max() < SIT_RATE_MAX, (rates.max(), [round(r['q_base'], 4) for r in sat])
        last = watch.truth[-5:]
        assert all(abs(r['q_base'] - caster) < CASTER_TOL_RAD for r in last), (caster, last)
        assert all(
            abs(r['current_left_a']) < SITTING_CURRENT_A
            and abs(r['current_right_a']) < SITTING_CURRENT_A
            for r in last
        ), [(round(r['current_left_a'], 2), round(r['x_m'], 3)) for r in watch.truth[n_truth:]]

        reply = client.operate(names.HALT)
        assert reply.success, reply.message
        wait_mode(client, 'safe_stop', 5.0)
        client.pause(1.0)
        assert all(
            r['current_left_a'] == 0.0 and r['current_right_a'] == 0.0 for r in watch.truth[-3:]
        )

        fault_pub.publish(fault(client, 'JRWheel: FAULT (test)'))
        client.pause(1.0)
        reply = client.operate(names.CONTROLLER_RECOVER)
        assert not reply.success and '/can_bridge/recover' in reply.message, reply.message
        assert 'JRWheel: FAULT (test)' in reply.message
        fault_pub.publish(fault(client, ''))
        client.pause(1.0)
        reply = client.operate(names.CONTROLLER_RECOVER)
        assert reply.success, reply.message
        wait_mode(client, 'sit', 10.0)
        assert client.modes[-4:] == ['sit_down', 'sit', 'safe_stop', 'sit']
    finally:
        client.close()
        rclpy.try_shutdown(context=context)
        nodes.stop(NODES)


@pytest.mark.timeout(120)
def test_names_move_with_the_namespace_and_read_only_parameters_refuse(tmp_path):
    """Under __ns:=/robot1 every service and topic of the controller is below /robot1; a run-time
    change of a read-only parameter is refused with a reason."""
    cmd = [sys.executable, '-m', 'krang_ros.entry', 'adrc_controller', '--ros-args']
    for f in params_files(sim=True):
        cmd += ['--params-file', f]
    cmd += ['-p', 'use_sim_time:=false', '-r', '__ns:=/robot1']
    proc = subprocess.Popen(
        cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    client, context = open_session_client()
    try:
        expected_services = {
            '/robot1' + n for n in (names.ENABLE, names.HALT, names.CONTROLLER_RECOVER)
        }
        expected_actions = {'/robot1' + n for n in (names.STAND_UP_ACTION, names.SIT_DOWN_ACTION)}
        expected_topics = {
            '/robot1' + n
            for n in (
                names.WHEEL_EFFORT_CMD,
                names.BALANCED_POSE,
                names.DIAGNOSTICS,
                names.MODE,
                names.BALANCE_CONVERGED,
                names.IMU,
                names.JOINT_STATES,
                names.BETA,
                names.POSE_TARGET,
                names.DRIVE_FAULT,
            )
        }

        def graph():
            return (
                {n for n, _ in client.get_service_names_and_types()},
                {n for n, _ in client.get_topic_names_and_types()},
            )

        client.spin_until(
            lambda: (
                expected_services <= graph()[0]
                and expected_topics <= graph()[1]
                and expected_actions <= {n for n, _ in get_action_names_and_types(client)}
            ),
            60.0,
            'the namespaced controller in the graph',
        )
        set_parameters = client.create_client(
            SetParameters, '/robot1/adrc_controller/set_parameters'
        )
        for name, value in (('adrc.eso.omega_o', 5.0), ('step_on_imu', True)):
            param = Parameter(name, value=value).to_parameter_msg()
            result = client.call(set_parameters, SetParameters.Request(parameters=[param]))
            assert not result.results[0].successful
            assert 'read-only' in result.results[0].reason, result.results[0].reason
    finally:
        client.close()
        rclpy.try_shutdown(context=context)
        proc.send_signal(2)
        out = proc.communicate(timeout=30)[0]
    assert 'Traceback' not in out, out[-3000:]
