"""Drives an online learning session over the node set's services and actions (used by `krang
demo`, the tests and the benches)."""

import time
import uuid

import rclpy
from action_msgs.msg import GoalStatus, GoalStatusArray
from krang_com_interfaces.action import MoveToNextPose, SitDown, StandUp
from krang_com_interfaces.msg import ControllerMode, MassModel
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.qos import qos_profile_action_status_default
from rclpy.signals import SignalHandlerOptions
from std_srvs.srv import SetBool, Trigger
from unique_identifier_msgs.msg import UUID

from krang_core import message_values, names

from . import topics
from .entry import STOP_REQUESTED
from .executor import StaticSingleThreadedExecutor

REFUSAL_RETRY_S = 3.0  # see SessionClient.learn_next_pose
ACTIONS = {
    names.STAND_UP_ACTION: StandUp,
    names.SIT_DOWN_ACTION: SitDown,
    names.MOVE_TO_NEXT_POSE: MoveToNextPose,
}
ENDED = {GoalStatus.STATUS_SUCCEEDED, GoalStatus.STATUS_ABORTED, GoalStatus.STATUS_CANCELED}

DISCOVERY_S = 30.0  # the longest wait for an action server to be discovered


class SessionError(RuntimeError):
    """The session could not continue (a node is missing, the robot did not balance, ...)."""


class ActionGoal:
    """A goal an action server accepted: its feedback as it comes, its status, its result."""

    def __init__(self, name, goal_id):
        self.name = name
        self.key = bytes(goal_id.uuid)
        self.feedback = []  # the Feedback messages, in order
        self.status = GoalStatus.STATUS_UNKNOWN  # from the status topic, then the result
        self.handle = None  # the ClientGoalHandle
        self.result = None  # the future of the GetResult answer

    @property
    def ended(self):
        return self.status in ENDED or (self.result is not None and self.result.done())

    @property
    def message(self):
        """The result's message once it came, else what the goal is doing."""
        if self.result is not None and self.result.done():
            return self.result.result().result.message
        return f'{self.name}: goal accepted'


class SessionClient(Node):
    def __init__(self, context=None, composed=None):
        """On its own, the client spins an executor of its own and waits in wall time. With
        `composed` (a krang_cli.composed.ComposedSimulation) it joins the composition's executor,
        each wait is a step of the whole simulated node set, its clock is simulated time, and a
        service's or action's answer is waited for with the physics held: a session then takes
        the same steps in every run."""
        super().__init__('krang_session', context=context)
        self.modes = []
        self.betas = []
        qos = topics.QOS
        self.create_subscription(
            ControllerMode, names.relative(names.MODE), self.on_mode, topics.LATCHED
        )
        self.create_subscription(
            MassModel, names.relative(names.BETA), self.on_beta, qos[names.BETA]
        )
        self.save = self.create_client(Trigger, names.relative(names.SAVE))
        self.enable = self.create_client(SetBool, names.relative(names.ENABLE))
        # the controller's operator controls (README, "Running on the robot")
        self.controls = {
            name: self.create_client(Trigger, names.relative(name))
            for name in (names.HALT, names.CONTROLLER_RECOVER)
        }
        self.actions = {
            name: ActionClient(self, action, names.relative(name))
            for name, action in ACTIONS.items()
        }
        # A goal's end is read from its action's status topic, which (a topic) a composition
        # delivers at once, where the GetResult answer comes a moment later: the session waits
        # for that answer with the physics held, from the step that ended the goal. The action
        # client's own goal status misses a goal ended before its acceptance came back (a refusal).
        self.goals = {}  # goal id -> ActionGoal, until its end is known
        for name in ACTIONS:
            self.create_subscription(
                GoalStatusArray,
                names.relative(name) + '/_action/status',
                self.on_goal_status,
                qos_profile_action_status_default,
            )
        self.standing = None  # the stand-up goal enable_controller sent, until it ends
        self.composed = composed
        if composed is None:
            self.spinner = StaticSingleThreadedExecutor(context=context)
            self.spinner.add_node(self)
            self.clock = time.monotonic
            self.advance = lambda: self.spinner.spin_once(timeout_sec=0.05)
        else:
            self.spinner = None
            composed.executor.add_node(self)
            self.clock = lambda: composed.sim_time
            self.advance = composed.advance

    @property
    def mode(self):
        return self.modes[-1] if self.modes else None

    def on_mode(self, msg):
        self.modes.append(message_values.mode_name(msg))

    def on_beta(self, msg):
        self.betas.append(list(msg.beta))

    def on_goal_status(self, msg):
        for status in msg.status_list:
            goal = self.goals.get(bytes(status.goal_info.goal_id.uuid))
            if goal is not None:
                goal.status = status.status

    def spin_until(self, condition, timeout, what):
        deadline = self.clock() + timeout
        while not condition():
            if self.clock() > deadline:
                raise SessionError(f'timed out after {timeout:.0f} s waiting for {what}')
            self._step()

    def pause(self, seconds):
        """Keep processing messages for `seconds`."""
        end = self.clock() + seconds
        while self.clock() < end:
            self._step()

    def _step(self):
        if STOP_REQUESTED.is_set():  # Ctrl-C (krang_ros.entry.interrupt): stop between steps
            raise KeyboardInterrupt
        self.advance()

    def answer(self, future, timeout, what):
        """The result of `future`, a service's (or an action's service's) answer."""
        if self.composed is None:
            self.spin_until(future.done, timeout, what)
            return future.result()
        # Composed: a topic message is in its reader's queue when publish returns, but a service
        # answer comes back through DDS a moment later (test/test_composed.py). The physics waits
        # for it, or the call would take a number of steps that depends on the scheduler.
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                raise SessionError(f'timed out after {timeout:.0f} s waiting for {what}')
            self.composed.deliver()
        return future.result()

    def call(self, client, request, timeout=10.0):
        self.spin_until(lambda: client.service_is_ready(), timeout, f'service {client.srv_name}')
        return self.answer(client.call_async(request), timeout, f'the answer of {client.srv_name}')

    def operate(self, name, timeout=10.0):
        """Call one of the controller's Trigger controls (names.HALT, ...); the reply."""
        return self.call(self.controls[name], Trigger.Request(), timeout)

    def send_goal(self, name, goal=None, timeout=10.0):
        """Send a goal to the action `name` (names.STAND_UP_ACTION, ...) and wait until it is
        accepted; the ActionGoal. A refused goal is accepted and ended at once, its result says
        why (krang_ros.actions)."""
        client = self.actions[name]
        # discovery of an action's five entities can take longer than a service's on a busy
        # graph: wait for it at least DISCOVERY_S, then `timeout` for the answer
        try:
            self.spin_until(client.server_is_ready, max(timeout, DISCOVERY_S), f'action {name}')
        except SessionError as err:
            raise SessionError(f'{err}; the graph shows {self.action_graph(name)}') from None
        goal_id = UUID(uuid=list(uuid.uuid4().bytes))
        sent = ActionGoal(name, goal_id)
        self.goals[sent.key] = sent
        future = client.send_goal_async(
            goal if goal is not None else ACTIONS[name].Goal(),
            feedback_callback=lambda msg: sent.feedback.append(msg.feedback),
            goal_uuid=goal_id,
        )
        try:
            handle = self.answer(future, timeout, f'the answer of {name}')
        except SessionError:
            del self.goals[sent.key]
            raise
        if not handle.accepted:
            del self.goals[sent.key]
            raise SessionError(f'{name} rejected the goal')
        sent.handle = handle
        sent.result = handle.get_result_async()
        return sent

    def action_graph(self, name):
        """What the graph shows of action `name`'s entities: a server is ready for this client
        only once all five match (its three services and the status and feedback topics)."""
        base = f'{name}/_action/'
        parts = [
            f'{s} servers {self.count_services(base + s)}'
            for s in ('send_goal', 'cancel_goal', 'get_result')
        ]
        parts += [
            f'{t} publishers {self.count_publishers(base + t)}' for t in ('status', 'feedback')
        ]
        return ', '.join(parts)

    def result(self, goal, timeout):
        """The Result of an ActionGoal, once it has ended (within `timeout`)."""
        self.spin_until(lambda: goal.ended, timeout, f'the result of {goal.name}')
        self.goals.pop(goal.key, None)
        answer = self.answer(goal.result, 10.0, f'the result of {goal.name}')
        goal.status = answer.status  # the status topic can come after the answer, over processes
        return answer.result

    def cancel(self, goal, timeout=10.0):
        """Ask to cancel an ActionGoal; True if the server accepted the cancel."""
        reply = self.answer(goal.handle.cancel_goal_async(), timeout, f'cancel of {goal.name}')
        return len(reply.goals_canceling) > 0

    def stand_up(self, timeout=10.0):
        return self.send_goal(names.STAND_UP_ACTION, timeout=timeout)

    def sit_down(self, timeout=10.0):
        return self.send_goal(names.SIT_DOWN_ACTION, timeout=timeout)

    def enable_controller(self, timeout):
        """Enable the balance controller as soon as it accepts (it refuses until sensor data
        flow), wait until it sits powered, then ask it to stand up (enable alone does not);
        wait_for_balance waits for that stand-up. A lost answer (DDS drops a service response
        whose reader it has not matched yet) is retried: enable is idempotent, and a stand-up is
        judged by the mode topic."""
        deadline = self.clock() + timeout

        def left():
            return max(1.0, deadline - self.clock())

        while True:
            try:
                reply = self.call(
                    self.enable, SetBool.Request(data=True), timeout=min(5.0, left())
                )
            except SessionError:
                if self.composed is not None or self.clock() > deadline:
                    raise  # composed, no answer is lost: a missing one is a fault
                continue
            if reply.success:
                break
            if self.clock() > deadline:
                raise SessionError(f'adrc_controller did not accept enable: {reply.message}')
            self.pause(1.0)
        self.spin_until(
            lambda: self.mode in ('sit', 'stand_up', 'balance'),
            left(),
            'the controller to sit powered',
        )
        while self.mode == 'sit':
            try:
                self.standing = self.stand_up(timeout=min(5.0, left()))
            except SessionError:
                if self.composed is not None or self.clock() > deadline:
                    raise
                continue
            return f'{reply.message}; standing up'
        return f'{reply.message}; already {self.mode}'

    def wait_for_balance(self, timeout):
        """Until the robot balances: the stand-up goal's result, if one was sent, and the mode
        topic (over processes it can come after the result; the pose server reads it too)."""
        if self.standing is not None:
            goal, self.standing = self.standing, None
            result = self.result(goal, timeout)
            if not result.success:
                raise SessionError(f'adrc_controller did not stand up: {result.message}')
        self.spin_until(
            lambda: self.mode is not None and 'balance' in self.mode.lower(),
            timeout,
            'the robot to stand up and balance (adrc_controller mode)',
        )

    def learn_next_pose(self, timeout):
        """Move to the next pose (the pose server's move_to_next_pose) and wait until the
        estimator has learned from the balanced pose that ends it; returns the result's text.
        The estimator's latched beta must be in first: it can reach this client after the goal
        (a stand-up of 1.5 s when the simulation runs at 3x real time) and would pass for the
        beta learned from the pose."""
        self.spin_until(
            lambda: len(self.betas) > 0, timeout, "com_estimator's current beta (latched)"
        )
        before = len(self.betas)
        result = self.result(self.send_goal(names.MOVE_TO_NEXT_POSE), timeout)
        # The pose server moves the robot only while it sees the controller balance, from the
        # same latched mode topic as this client, which can reach it a moment later (a stand-up of
        # 1.4 s in an unpaced simulation): a refusal while this client sees balance is asked again
        # for up to REFUSAL_RETRY_S.
        retry_until = self.clock() + REFUSAL_RETRY_S
        while (
            not result.success
            and result.message.startswith('refused')
            and self.mode == 'balance'
            and self.clock() < retry_until
        ):
            self.pause(0.2)
            result = self.result(self.send_goal(names.MOVE_TO_NEXT_POSE), timeout)
        if not result.success:
            raise SessionError(f'move_to_next_pose: {result.message}')
        self.spin_until(
            lambda: len(self.betas) > before,
            timeout,
            f'a new beta after "{result.message}"',
        )
        return result.message

    def close(self):
        if self.spinner is not None:
            self.spinner.shutdown()
        for client in self.actions.values():
            client.destroy()
        self.destroy_node()


def open_session_client():
    """A client in a context of its own. Ctrl-C stays the caller's (``krang demo`` reports it):
    rclpy's signal handlers are not installed, as in the nodes (``spin.run_node``)."""
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    return SessionClient(context=context), context
