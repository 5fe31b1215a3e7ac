"""The one way our nodes run: init, spin until Ctrl-C or shutdown, then close and shut down
cleanly, with exit code 0 and no traceback however early the signal comes. rclpy's own signal
handlers are not installed: krang_ros.entry's handle the signals, and the loop checks
STOP_REQUESTED every STOP_CHECK_S. rclpy's signal thread triggers a guard condition of every
executor on a signal, and it did so on one that the stop had already destroyed: a pose server
ended with SIGSEGV on SIGINT (docs/architecture.md)."""

import sys

import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.signals import SignalHandlerOptions
from rclpy.executors import ExternalShutdownException, TimeoutException

from krang_core.params import ParameterError

from .entry import STOP_REQUESTED, settle_garbage_collector
from .executor import StaticSingleThreadedExecutor


#: The longest a node's loop waits before it checks STOP_REQUESTED: a signal's handler runs once
#: the wait returns, so a node stops within this of a SIGINT or SIGTERM
STOP_CHECK_S = 0.5


def run_node(node_class, args=None):
    """Spin one node; `node.close()` (if the node has one) releases its hardware before
    destruction. A SIGINT or SIGTERM while the node is still being built (rclpy then shuts the
    context down under the constructor, whose next ROS call fails) is a clean exit too."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = StaticSingleThreadedExecutor()
    try:
        node = without_qos_events(node_class())
        executor.add_node(node)
        settle_garbage_collector()
        while rclpy.ok() and not STOP_REQUESTED.is_set():
            executor.spin_once(timeout_sec=STOP_CHECK_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ParameterError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    except Exception:
        if rclpy.ok():
            raise
        # the context was shut down by a signal under a ROS call: a requested stop, not a fault
    finally:
        if node is not None:
            executor.remove_node(node)
            if hasattr(node, 'close'):
                node.close()
            node.destroy_node()
        rclpy.try_shutdown()
        executor.shutdown()
    return 0


def without_qos_events(node):
    """`node` with the QoS event handlers rclpy gives each of its publishers and subscriptions
    left out of its executor's wait set. They only log that a peer requests an incompatible QoS,
    which the peer's own handlers log as well (a `ros2 topic echo` with the wrong reliability
    says so); our nodes share one QoS table (topics.py). But rclpy re-adds every handler to the
    wait set at each wake, more than half of the entities of a node: without them the sample ->
    command latency of the robot's control path fell from 1.32-1.63x to 1.22-1.31x the bare
    chain's at p50 (bench_ros_latency.py --robot). A group that never runs keeps them out;
    removing them from the node would break its destroy_publisher."""
    never = Polled()
    for endpoint in (*node.publishers, *node.subscriptions):
        for handler in endpoint.event_handlers:
            handler.callback_group = never
    return node


class Polled(CallbackGroup):
    """A callback group the executor never runs: its subscriptions cost no wake of the executor
    (about 0.2 ms of CPU each in rclpy's SingleThreadedExecutor here) and are read by
    `take_latest` when their data is needed, e.g. a topic a control step reads at its own
    rate."""

    def can_execute(self, entity):
        return False

    def beginning_execution(self, entity):
        return False

    def ending_execution(self, entity):
        pass


def take_waiting(subscription):
    """Every message waiting on `subscription`, oldest first: on a `Polled` one, or on one whose
    callback is running (the executor then finds nothing more to take)."""
    waiting = []
    with subscription.handle:
        while True:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
            if taken is None:
                return waiting
            waiting.append(taken[0])


def take_latest(subscription):
    """The newest message waiting on a `Polled` subscription (older ones are dropped), or None."""
    waiting = take_waiting(subscription)
    return waiting[-1] if waiting else None


def run_ready(executor):
    """Run every callback of `executor` that is ready now, and those they make ready, without
    waiting; the number run (0: nothing was ready)."""
    ran = 0
    while True:
        try:
            handler, _, _ = executor.wait_for_ready_callbacks(timeout_sec=0)
        except TimeoutException:
            return ran
        handler()
        if handler.exception() is not None:
            raise handler.exception()
        ran += 1


def spin_until_shutdown(executor):
    """executor.spin() for a thread of its own, ended by shutting its context down (rclpy raises
    ExternalShutdownException then). Shut the context down first and join the thread before
    executor.shutdown(): shutting the executor down under a spinning thread races rclpy's own
    guard conditions (README, Known issues)."""
    try:
        executor.spin()
    except ExternalShutdownException:
        pass
