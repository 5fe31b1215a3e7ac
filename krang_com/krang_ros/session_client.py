"""Drives an online learning session over the node set's services (used by `krang demo` and the
tests)."""

import time

import rclpy
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import SetBool, Trigger

from krang_core import names

from . import topics
from .entry import STOP_REQUESTED
from .executor import StaticSingleThreadedExecutor

REFUSAL_RETRY_S = 3.0  # see SessionClient.learn_next_pose


class SessionError(RuntimeError):
    """The session could not continue (a node is missing, the robot did not balance, ...)."""


class SessionClient(Node):
    def __init__(self, context=None, composed=None):
        """On its own, the client spins an executor of its own and waits in wall time. With
        `composed` (a krang_cli.composed.ComposedSimulation) it joins the composition's executor,
        each wait is a step of the whole simulated node set, its clock is simulated time, and a
        service call waits for its answer with the physics held: a session then takes the same
        steps in every run."""
        super().__init__('krang_session', context=context)
        self.modes = []
        self.betas = []
        qos = topics.QOS
        self.create_subscription(String, names.relative(names.MODE), self.on_mode, topics.LATCHED)
        self.create_subscription(
            Float64MultiArray, names.relative(names.BETA), self.on_beta, qos[names.BETA]
        )
        self.next_pose = self.create_client(Trigger, names.relative(names.NEXT_POSE))
        self.save = self.create_client(Trigger, names.relative(names.SAVE))
        self.enable = self.create_client(SetBool, names.relative(names.ENABLE))
        # the controller's operator controls (README, "Running on the robot")
        self.controls = {
            name: self.create_client(Trigger, names.relative(name))
            for name in (names.STAND_UP, names.SIT_DOWN, names.HALT, names.CONTROLLER_RECOVER)
        }
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
        self.modes.append(msg.data)

    def on_beta(self, msg):
        self.betas.append(list(msg.data))

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

    def call(self, client, request, timeout=10.0):
        self.spin_until(lambda: client.service_is_ready(), timeout, f'service {client.srv_name}')
        future = client.call_async(request)
        if self.composed is None:
            self.spin_until(future.done, timeout, f'the answer of {client.srv_name}')
            return future.result()
        # Composed: a topic message is in its reader's queue when publish returns, but a service
        # answer comes back through DDS a moment later (test/test_composed.py). The physics waits
        # for it, or the call would take a number of steps that depends on the scheduler.
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                raise SessionError(
                    f'timed out after {timeout:.0f} s waiting for the answer of {client.srv_name}'
                )
            self.composed.deliver()
        return future.result()

    def operate(self, name, timeout=10.0):
        """Call one of the controller's Trigger controls (names.STAND_UP, ...); the reply."""
        return self.call(self.controls[name], Trigger.Request(), timeout)

    def enable_controller(self, timeout):
        """Enable the balance controller as soon as it accepts (it refuses until sensor data
        flow), wait until it sits powered, then ask it to stand up (enable alone does not).
        A lost answer (DDS drops a service response whose reader it has not matched yet) is
        retried: enable is idempotent, and a stand_up is judged by the mode topic."""
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
                stand = self.operate(names.STAND_UP, timeout=min(5.0, left()))
            except SessionError:
                if self.composed is not None or self.clock() > deadline:
                    raise
                continue
            if not stand.success:
                raise SessionError(f'adrc_controller did not stand up: {stand.message}')
            return f'{reply.message}; {stand.message}'
        return f'{reply.message}; already {self.mode}'

    def wait_for_balance(self, timeout):
        self.spin_until(
            lambda: self.mode is not None and 'balance' in self.mode.lower(),
            timeout,
            'the robot to stand up and balance (adrc_controller mode)',
        )

    def learn_next_pose(self, timeout):
        """Command the next pose and wait until the estimator has learned from it; returns the
        reply text. The estimator's latched beta must be in first: it can reach this client after
        the call (a stand-up of 1.5 s when the simulation runs at 3x real time) and would pass for
        the beta learned from the pose."""
        self.spin_until(
            lambda: len(self.betas) > 0, timeout, "com_estimator's current beta (latched)"
        )
        before = len(self.betas)
        reply = self.call(self.next_pose, Trigger.Request())
        # The pose server moves the robot only while it sees the controller balance, from the
        # same latched mode topic as this client, which can reach it a moment later (a stand-up of
        # 1.4 s in an unpaced simulation): a refusal while this client sees balance is asked again
        # for up to REFUSAL_RETRY_S.
        retry_until = self.clock() + REFUSAL_RETRY_S
        while not reply.success and self.mode == 'balance' and self.clock() < retry_until:
            self.pause(0.2)
            reply = self.call(self.next_pose, Trigger.Request())
        if not reply.success:
            raise SessionError(f'next_pose refused: {reply.message}')
        self.spin_until(
            lambda: len(self.betas) > before,
            timeout,
            f'a balanced pose and a new beta after "{reply.message}"',
        )
        return reply.message

    def close(self):
        if self.spinner is not None:
            self.spinner.shutdown()
        self.destroy_node()


def open_session_client():
    context = rclpy.Context()
    rclpy.init(context=context)
    return SessionClient(context=context), context
