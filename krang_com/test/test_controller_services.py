"""The controller's operator services over real processes (sim_krang, can_bridge, adrc_controller):
enable sits powered without standing, stand_up balances, sit_down puts the robot back on its caster
without a fall, halt zeroes the current, recover is refused while the bridge reports a drive fault;
and the controller's names move with its namespace (README, "Running on the robot")."""

import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('msgpack')  # python-can's udp_multicast needs it

from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Float64MultiArray, String  # noqa: E402
from std_srvs.srv import SetBool  # noqa: E402

from krang_cli.node_set import params_files  # noqa: E402
from krang_cli.processes import NodeSet  # noqa: E402
from krang_model.drivetrain import drivetrain  # noqa: E402
from krang_model.robot import load_krang  # noqa: E402
from krang_core import names  # noqa: E402
from krang_ros import topics  # noqa: E402
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
        fault_pub = client.create_publisher(String, names.DRIVE_FAULT, topics.LATCHED)
        enable = client.enable
        for _ in range(60):  # refused until the sensor data flow
            try:
                if client.call(enable, SetBool.Request(data=True), timeout=5.0).success:
                    break
            except SessionError:  # a lost first answer (SessionClient.enable_controller): retry
                continue
            client.pause(1.0)
        wait_mode(client, 'sit', 10.0)
        client.pause(3.0)
        assert client.mode == 'sit', 'enable must not stand the robot up'
        reply = client.operate(names.STAND_UP)
        assert reply.success and reply.message.startswith('started'), reply.message
        wait_mode(client, 'balance', 120.0)
        reply = client.call(enable, SetBool.Request(data=False))
        assert not reply.success and 'use sit_down or halt' in reply.message
        reply = client.operate(names.STAND_UP)
        assert not reply.success and 'already balancing' in reply.message
        client.pause(3.0)

        n_truth = len(watch.truth)
        reply = client.operate(names.SIT_DOWN)
        assert reply.success, reply.message
        wait_mode(client, 'sit', 20.0)
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

        fault_pub.publish(String(data='JRWheel: FAULT (test)'))
        client.pause(1.0)
        reply = client.operate(names.CONTROLLER_RECOVER)
        assert not reply.success and '/can_bridge/recover' in reply.message, reply.message
        assert 'JRWheel: FAULT (test)' in reply.message
        fault_pub.publish(String(data=''))
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
            '/robot1' + n
            for n in (
                names.ENABLE,
                names.STAND_UP,
                names.SIT_DOWN,
                names.HALT,
                names.CONTROLLER_RECOVER,
            )
        }
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
            lambda: expected_services <= graph()[0] and expected_topics <= graph()[1],
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
