"""The session client counts a pose as learned only from a beta published after it: the
estimator's latched beta, reaching the client late, must not pass for a learned one (a demo
stopped with "a move is still under way" when the simulation got fast enough for that race)."""

import threading
import time

import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')

from krang_com_interfaces.action import MoveToNextPose  # noqa: E402
from krang_com_interfaces.msg import MassModel  # noqa: E402
from rclpy.action import ActionServer  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402

from krang_core import names  # noqa: E402
from krang_ros import topics  # noqa: E402
from krang_ros.session_client import open_session_client  # noqa: E402
from krang_ros.spin import spin_until_shutdown  # noqa: E402

LATCHED_AFTER_S = 0.5  # the estimator's initial beta comes this late
LEARNED_AFTER_S = 1.0  # the beta learned from the pose, after the move's result


def test_latched_beta_arriving_late_is_not_taken_for_a_learned_one():
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('fake_estimator_and_pose_server', context=context)
    beta_pub = node.create_publisher(MassModel, names.relative(names.BETA), topics.QOS[names.BETA])
    calls = []

    def publish_once(delay, value):
        def fire():
            timer.cancel()
            beta_pub.publish(MassModel(beta=[value]))

        timer = node.create_timer(delay, fire)

    def move(goal_handle):  # the balanced pose at once; the estimator learns from it later
        calls.append(time.monotonic())
        publish_once(LEARNED_AFTER_S, 2.0)
        goal_handle.succeed()
        return MoveToNextPose.Result(success=True, message='pose 1')

    ActionServer(node, MoveToNextPose, names.relative(names.MOVE_TO_NEXT_POSE), move)
    publish_once(LATCHED_AFTER_S, 1.0)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    spinner = threading.Thread(target=spin_until_shutdown, args=(executor,), daemon=True)
    spinner.start()
    client, client_context = open_session_client()
    try:
        start = time.monotonic()
        client.learn_next_pose(timeout=10.0)
        done = time.monotonic()
        assert [b[0] for b in client.betas] == [1.0, 2.0]
        assert calls and calls[0] >= start + LATCHED_AFTER_S * 0.9
        assert done >= calls[0] + LEARNED_AFTER_S * 0.9
    finally:
        client.close()
        rclpy.try_shutdown(context=client_context)
        rclpy.try_shutdown(context=context)  # ends the spin first (spin_until_shutdown)
        spinner.join(5.0)
        executor.shutdown()
        node.destroy_node()


def test_a_server_not_ready_is_described_by_what_the_graph_shows():
    """A stand_up that times out says which of the action's five entities the graph shows: none
    before a server exists, all five once one does (a server half in the graph was seen once, and
    the timeout alone could not tell)."""
    from krang_com_interfaces.action import StandUp

    client, client_context = open_session_client()
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('fake_controller', context=context)
    try:
        none = client.action_graph(names.STAND_UP_ACTION)
        assert none == (
            'send_goal servers 0, cancel_goal servers 0, get_result servers 0, '
            'status publishers 0, feedback publishers 0'
        )
        ActionServer(node, StandUp, names.STAND_UP_ACTION, lambda handle: StandUp.Result())
        client.spin_until(
            lambda: '0' not in client.action_graph(names.STAND_UP_ACTION), 30.0, 'the server'
        )
        assert client.action_graph(names.STAND_UP_ACTION) == none.replace('0', '1')
    finally:
        client.close()
        rclpy.try_shutdown(context=client_context)
        node.destroy_node()
        rclpy.try_shutdown(context=context)
