"""An arm module that stops answering while the robot balances, over the node set as processes
(sim_krang, can_bridge, adrc_controller; test_sim_node_set's rig): sim_krang silences LJ2's
PowerCube module. The bridge latches the arm fault on /can_bridge/arm_fault and keeps LJ2 in
/joint_states at its last position, the controller keeps balancing (no safe stop, current on the
wheels, the pitch at its balance), and the bridge's recover clears the fault only once the module
answers again."""

import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('msgpack')  # python-can's udp_multicast needs it

from krang_com_interfaces.msg import ArmFault  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from krang_core import names  # noqa: E402
from krang_core.message_values import arm_fault_reason  # noqa: E402
from krang_ros import topics  # noqa: E402
from krang_ros.session_client import DISCOVERY_S  # noqa: E402
from test_sim_node_set import balancing_robot, silence  # noqa: E402, F401


def silence_none(client):
    set_parameters = client.create_client(SetParameters, '/sim_krang/set_parameters')
    param = Parameter('silent_devices', Parameter.Type.STRING_ARRAY, []).to_parameter_msg()
    reply = client.call(set_parameters, SetParameters.Request(parameters=[param]))
    assert reply.results[0].successful, reply.results[0].reason


@pytest.mark.timeout(240)
def test_a_silent_arm_module_leaves_the_robot_balancing(balancing_robot):  # noqa: F811
    client, observer, devices = balancing_robot
    arm = {}
    client.create_subscription(
        ArmFault,
        names.ARM_FAULT,
        lambda m: arm.update(reason=arm_fault_reason(m), joints=list(m.joints)),
        topics.LATCHED,
    )
    # the latched state reaches a new reader once discovery matched it (krang_ros.session_client)
    client.spin_until(lambda: arm.get('reason') == '', DISCOVERY_S, 'the clear arm fault')
    assert client.mode == 'balance'
    observer.safe_stop_at = None  # the one before the enable does not count
    silence(client, 'LJ2')
    client.spin_until(lambda: bool(arm.get('reason')), 10.0, 'the arm fault')
    assert arm['joints'] == ['LJ2'] and 'not answering' in arm['reason'], arm
    client.spin_until(lambda: observer.fault_at is not None, 10.0, 'the silence reported')
    t0 = observer.fault_at
    client.pause(5.0)
    assert observer.safe_stop_at is None and client.mode == 'balance'
    after = [row for row in observer.truth_rows if row['t'] > t0]
    assert after[-1]['t'] - t0 > 3.0, 'the simulation did not run on'
    assert any(row['current_left_a'] != 0.0 for row in after[-10:]), 'no current on the wheels'
    # the robot was still swaying from its stand-up (up to 0.06 rad); it settles at its balance
    late = [r for r in after if r['t'] > after[-1]['t'] - 2.0]
    assert max(abs(r['q_base'] - r['balance_pitch']) for r in late) < 0.02

    recover = client.create_client(Trigger, names.BRIDGE_RECOVER)
    refused = client.call(recover, Trigger.Request(), timeout=15.0)
    assert not refused.success and 'not answering' in refused.message, refused.message
    silence_none(client)
    client.pause(1.0)
    assert arm['reason'], 'answering again cleared the arm fault without a recover'
    accepted = client.call(recover, Trigger.Request(), timeout=15.0)
    assert accepted.success, accepted.message
    client.spin_until(lambda: arm.get('reason') == '', 10.0, 'the arm fault cleared')
    assert client.mode == 'balance'
