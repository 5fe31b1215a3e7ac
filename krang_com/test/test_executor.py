"""krang_ros.executor against its reference, rclpy's SingleThreadedExecutor: the same scripted
traffic must run the same callbacks in the same order on both; entities and nodes added or removed
while it spins are served or dropped; a destroyed entity is released; a coroutine callback that
awaits another call completes; a shutdown wakes a blocked spin."""

import threading
import time

import pytest

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip('rclpy')

from rclpy.callback_groups import ReentrantCallbackGroup  # noqa: E402
from rclpy.exceptions import InvalidHandle  # noqa: E402
from rclpy.executors import (  # noqa: E402
    ExternalShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from std_msgs.msg import Int32  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from krang_ros.executor import StaticSingleThreadedExecutor  # noqa: E402
from krang_ros.spin import Polled, run_ready, take_waiting  # noqa: E402

EXECUTORS = {'rclpy': SingleThreadedExecutor, 'static': StaticSingleThreadedExecutor}


def spinning_node(context, name):
    """Our executor with one node that subscribes to `name`."""
    executor = StaticSingleThreadedExecutor(context=context)
    node = rclpy.create_node(name, context=context)
    node.create_subscription(Int32, name, lambda m: None, 10)
    executor.add_node(node)
    return executor, node


def traffic(executor_class, context):
    """A scripted burst on one node (rclpy orders nodes by a set, not by anything we control):
    three topics with queued messages, a due timer and a cancelled one, a triggered guard
    condition, a service request and its answer, a subscription destroyed and one created by a
    callback. The callbacks that ran, in order."""
    ran = []
    node = rclpy.create_node('order', context=context)
    pubs = {name: node.create_publisher(Int32, f'order_{name}', 10) for name in 'xyz'}

    def on(name):
        return lambda msg: ran.append(f'{name}{msg.data}')

    node.create_subscription(Int32, 'order_x', on('x'), 10)
    doomed = node.create_subscription(Int32, 'order_y', on('y'), 10)
    node.create_subscription(Int32, 'order_z', on('z'), 10)

    def tick():
        """Once: destroys order_y's subscription (its queued messages are never taken) and
        creates one on order_w (served from the next wait on)."""
        ran.append('tick')
        timer.cancel()
        node.destroy_subscription(doomed)
        node.create_subscription(Int32, 'order_w', on('w'), 10)
        pubs['w'] = node.create_publisher(Int32, 'order_w', 10)

    timer = node.create_timer(0.001, tick)
    cancelled = node.create_timer(0.001, lambda: ran.append('cancelled'))
    cancelled.cancel()
    guard = node.create_guard_condition(lambda: ran.append('guard'))
    node.create_service(Trigger, 'order_srv', lambda req, res: (ran.append('srv'), res)[1])
    client = node.create_client(Trigger, 'order_srv')
    executor = executor_class(context=context)
    executor.add_node(node)
    assert client.wait_for_service(timeout_sec=5.0)
    for i in range(3):
        for pub in pubs.values():
            pub.publish(Int32(data=i))
    guard.trigger()
    future = client.call_async(Trigger.Request())
    future.add_done_callback(lambda _: ran.append('answer'))
    time.sleep(0.01)  # the timer is due
    for _ in range(4):
        run_ready(executor)
    pubs['w'].publish(Int32(data=7))
    pubs['y'].publish(Int32(data=7))  # nobody listens any more
    deadline = time.monotonic() + 5.0
    while not future.done() and time.monotonic() < deadline:
        run_ready(executor)
    run_ready(executor)
    executor.shutdown()
    node.destroy_node()
    return ran


def test_the_same_traffic_runs_the_same_callbacks_in_the_same_order(context):
    reference = traffic(SingleThreadedExecutor, context)
    static = traffic(StaticSingleThreadedExecutor, context)
    assert static == reference
    # and the script did what it meant to (so that the comparison is not of two empty lists)
    assert reference.count('tick') == 1 and 'cancelled' not in reference
    for expected in ('x0', 'x2', 'z2', 'guard', 'srv', 'answer', 'w7'):
        assert expected in reference, reference
    assert not any(name.startswith('y') for name in reference), reference


@pytest.mark.parametrize('name', sorted(EXECUTORS))
def test_nodes_added_and_removed_while_spinning(name, context):
    executor = EXECUTORS[name](context=context)
    talker = rclpy.create_node('talker', context=context)
    pub = talker.create_publisher(Int32, 'membership', 10)
    executor.add_node(talker)
    got = []
    listener = rclpy.create_node('listener', context=context)
    listener.create_subscription(Int32, 'membership', lambda m: got.append(m.data), 10)
    run_ready(executor)
    pub.publish(Int32(data=1))
    run_ready(executor)
    assert got == []  # not added yet: its callbacks do not run
    executor.add_node(listener)
    run_ready(executor)
    assert got == [1]
    executor.remove_node(listener)
    pub.publish(Int32(data=2))
    run_ready(executor)
    assert got == [1]
    executor.shutdown()
    listener.destroy_node()
    talker.destroy_node()


def test_polled_subscriptions_never_run_and_keep_their_messages(context):
    executor = StaticSingleThreadedExecutor(context=context)
    node = rclpy.create_node('polled', context=context)
    pub = node.create_publisher(Int32, 'polled', 10)
    got = []
    sub = node.create_subscription(
        Int32, 'polled', lambda m: got.append(m.data), 10, callback_group=Polled()
    )
    executor.add_node(node)
    for i in range(3):
        pub.publish(Int32(data=i))
        assert run_ready(executor) == 0
    assert got == [] and [m.data for m in take_waiting(sub)] == [0, 1, 2]
    executor.shutdown()
    node.destroy_node()


def test_an_entity_destroyed_while_kept_is_released(context):
    """The executor holds the handles of the entities it waits on between waits; a destroyed one
    must be really destroyed at the next wait, and every one when its node is removed."""
    executor = StaticSingleThreadedExecutor(context=context)
    node = rclpy.create_node('releases', context=context)
    sub = node.create_subscription(Int32, 'releases', lambda m: None, 10)
    timer = node.create_timer(10.0, lambda: None)
    executor.add_node(node)
    run_ready(executor)  # waits once: the handles are held from here
    node.destroy_subscription(sub)
    run_ready(executor)
    with pytest.raises(InvalidHandle):
        with sub.handle:
            pass
    with timer.handle:  # still held and alive
        pass
    executor.remove_node(node)
    node.destroy_timer(timer)
    with pytest.raises(InvalidHandle):
        with timer.handle:
            pass
    executor.shutdown()
    node.destroy_node()


def test_an_entity_destroyed_from_another_thread_during_a_wait(context):
    """Destroyed while the executor blocks on it: the wait ends (the executor is woken), the
    entity is released after it, and the executor goes on with the others."""
    executor = StaticSingleThreadedExecutor(context=context)
    node = rclpy.create_node('destroyed_in_wait', context=context)
    pub = node.create_publisher(Int32, 'destroyed_in_wait', 10)
    got = []
    sub = node.create_subscription(Int32, 'destroyed_in_wait', lambda m: got.append(m.data), 10)
    other = node.create_subscription(Int32, 'still_here', lambda m: got.append(-m.data), 10)
    other_pub = node.create_publisher(Int32, 'still_here', 10)
    executor.add_node(node)
    threading.Timer(0.2, lambda: node.destroy_subscription(sub)).start()
    executor.spin_once(timeout_sec=2.0)  # woken by the destruction, long before 2 s
    pub.publish(Int32(data=1))
    other_pub.publish(Int32(data=2))
    run_ready(executor)
    assert got == [-2]
    with pytest.raises(InvalidHandle):
        with sub.handle:
            pass
    del other
    executor.shutdown()
    node.destroy_node()


@pytest.mark.parametrize('name', sorted(EXECUTORS))
def test_a_coroutine_callback_awaits_a_call_to_another_service(name, context):
    """The classic nested call: a service whose async callback calls another service. While it
    awaits, a task is in progress and callback groups decide what may run."""
    executor = EXECUTORS[name](context=context)
    node = rclpy.create_node('nested', context=context)
    group = ReentrantCallbackGroup()  # the awaited answer must be taken while outer awaits
    node.create_service(
        Trigger,
        'inner',
        lambda req, res: (setattr(res, 'message', 'inner'), res)[1],
        callback_group=group,
    )
    inner = node.create_client(Trigger, 'inner', callback_group=group)

    async def outer_callback(request, response):
        answer = await inner.call_async(Trigger.Request())
        response.success, response.message = True, f'outer({answer.message})'
        return response

    node.create_service(Trigger, 'outer', outer_callback, callback_group=group)
    outer = node.create_client(Trigger, 'outer')
    executor.add_node(node)
    assert outer.wait_for_service(timeout_sec=5.0)
    future = outer.call_async(Trigger.Request())
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    assert future.done() and future.result().message == 'outer(inner)'
    executor.shutdown()
    node.destroy_node()


def test_a_shutdown_wakes_a_blocked_spin(context):
    executor, node = spinning_node(context, 'blocked')
    ended = []

    def spin():
        try:
            executor.spin()
        except ExternalShutdownException:
            ended.append('shutdown')

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    time.sleep(0.2)
    assert spinner.is_alive()
    rclpy.try_shutdown(context=context)
    spinner.join(5.0)
    assert not spinner.is_alive() and ended == ['shutdown']
    executor.shutdown()
    node.destroy_node()


def test_a_timeout_with_nothing_ready(context):
    executor, node = spinning_node(context, 'idle')
    with pytest.raises(TimeoutException):
        executor.wait_for_ready_callbacks(timeout_sec=0)
    start = time.monotonic()
    executor.spin_once(timeout_sec=0.1)
    assert time.monotonic() - start >= 0.1
    executor.shutdown()
    node.destroy_node()


@pytest.mark.parametrize('name', sorted(EXECUTORS))
def test_a_callbacks_error_comes_out_of_spin_once_and_an_async_callback_runs(name, context):
    """Ours runs a plain subscription or timer callback directly, without rclpy's Task: an
    exception in one still comes out of spin_once as under rclpy's executor, and an async
    callback still runs as a coroutine."""
    executor = EXECUTORS[name](context=context)
    node = rclpy.create_node('errors', context=context)
    got = []

    def fails(msg):
        raise ValueError(f'bad {msg.data}')

    async def later(msg):
        got.append(msg.data)

    node.create_subscription(Int32, 'errors_plain', fails, 10)
    node.create_subscription(Int32, 'errors_async', later, 10)
    node.create_timer(0.01, lambda: got.append('tick'))
    plain = node.create_publisher(Int32, 'errors_plain', 10)
    coroutine = node.create_publisher(Int32, 'errors_async', 10)
    executor.add_node(node)
    try:
        plain.publish(Int32(data=7))
        with pytest.raises(ValueError, match='bad 7'):
            for _ in range(100):
                executor.spin_once(timeout_sec=0.05)
        coroutine.publish(Int32(data=8))
        deadline = time.monotonic() + 5.0
        while not (8 in got and 'tick' in got) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        assert 8 in got and 'tick' in got, got
    finally:
        executor.shutdown()
        node.destroy_node()
