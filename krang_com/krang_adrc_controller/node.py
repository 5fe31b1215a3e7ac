"""adrc_controller: the balance controller on ROS topics (thin shell over
controller.BalanceController). Control runs from the latest imu/data and joint_states, either on
a timer at `rate_hz` (the node's clock: wall time, or /clock with use_sim_time) or, with
`step_on_imu`, once per imu/data sample (the 2018 kore loop also waited for each IMU message).
Stepping on the sample removes the phase lag between two free-running loops at the same rate:
the timer fired just before the bridge's next sample arrived and so used a sample one period old
(measured over DDS at 100 Hz: median 10 ms, p90 25 ms of extra sample age). The timer then only
watches: if no sample has driven the loop for three periods it steps anyway, so stale data still
end in a safe stop; each sample restarts it, so its callback never runs while samples flow
(rcl's reset still wakes the executor once, with nothing to run; letting the timer fire instead
measured the same). /joint_states is read by each step, not by a callback of its own: one
executor wake per sample. Both are taken as their serialized bytes and read by krang_ros.wire,
and the wheel command goes out as bytes: rclpy's message objects cost 50-70 us each here. If
either input is older than `stale_timeout_s`, the controller is told the data are stale and
commands zero torque (safe stop) until recovered.

The operator's controls are node-private (README, "Running on the robot"): the services ~/enable
(SetBool), ~/halt and ~/recover (Trigger) answer at once, accepted or refused with the reason; the
actions ~/stand_up (StandUp) and ~/sit_down (SitDown) give feedback while the mode machine works
and their result when it gets there or leaves (krang_adrc_controller.goals, krang_ros.actions).
Their callbacks and the feedback timer are a callback group of their own, and the control step
only hands them the steps with events. An active can_bridge/drive_fault forces a safe stop.
A stand-up caught back on its caster publishes the controller's estimate of the CoM-angle error
on the latched ~/stand_estimate (StandEstimate), stamped as the mode change to sit, for the pose
server's re-pose before the retry. Topics are relative (joint_states, imu/data, wheel_effort_cmd,
balanced_pose, diagnostics, ...), so the node moves with __ns; its services, actions and ~/mode,
~/balance_converged, ~/stand_estimate move with __node too.
"""

import sys

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from krang_com_interfaces.action import SitDown, StandUp
from krang_com_interfaces.msg import (
    BalancedPose,
    ControllerMode,
    DriveFault,
    MassModel,
    StandEstimate,
)
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger

from krang_model.beta import load_beta
from krang_model.robot import load_krang
from krang_core import message_values, names, params
from krang_core.log import Throttled
from krang_core.names import WHEEL_JOINTS as WHEELS
from krang_core.pitch import pitch_from_quaternion, pitch_from_specific_force
from krang_ros import messages, realtime, topics, trace, wire
from krang_ros.actions import HeldGoals
from krang_ros.params import declare
from krang_ros.spin import Polled, run_node, take_latest, take_waiting

from .controller import BalanceController, ControllerConfig
from .goals import SIT_DOWN, STAND_UP, OperatorGoal
from .modes import MODE_CODES
from .samples import ControlSample, JointMotion, Reply

#: the node's own parameters besides ControllerConfig's: name -> (type, default, description)
NODE_PARAMETERS = {
    'step_on_imu': (
        bool,
        False,
        'step once per imu/data sample (the timer only watches); '
        'false = step on a timer at rate_hz',
    ),
    'initial_beta': (
        str,
        '',
        'beta file to balance with until com_estimator publishes one '
        "('' = the URDF's nominal beta)",
    ),
}


def describe_parameters():
    """One line per parameter, 'name (type, default): description' (`adrc_controller --help`)."""
    rows = [
        (leaf.name, leaf.kind, leaf.default, leaf.doc) for leaf in params.leaves(ControllerConfig)
    ]
    rows += [(name, kind, default, doc) for name, (kind, default, doc) in NODE_PARAMETERS.items()]
    own = [f'{name} ({kind.__name__}, {default!r}): {doc}' for name, kind, default, doc in rows]
    return own + params.describe(realtime.SchedulingParams)


#: with step_on_imu the watch timer steps once no sample came for this many control periods
WATCH_PERIODS = 3.0
#: feedback of the stand_up and sit_down actions while a goal is active [Hz]
FEEDBACK_HZ = 10.0


class AdrcControllerNode(Node):
    def __init__(self, **kwargs):
        super().__init__('adrc_controller', **kwargs)
        self.robot = load_krang()
        # every ControllerConfig leaf is a dotted ROS parameter (adrc.eso.omega_o; controller.yaml)
        self.config = declare(self, ControllerConfig)
        self.stale_timeout = self.config.safety.stale_timeout_s
        own = {
            name: self.declare_parameter(
                name, default, ParameterDescriptor(name=name, description=doc, read_only=True)
            ).value
            for name, (_, default, doc) in NODE_PARAMETERS.items()
        }
        self.step_on_imu = bool(own['step_on_imu'])
        realtime.declare_thread_priority(self)
        beta_file = own['initial_beta']
        beta = load_beta(beta_file, self.robot) if beta_file else self.robot.nominal_beta
        self.controller = BalanceController(self.robot, beta, self.config)
        self.imu = None
        self.joint_state = None
        self._warn_joints = Throttled(self.get_logger().warning, 5.0)
        self._warn_imu = Throttled(self.get_logger().warning, 5.0)
        self._joint_names, self._joint_index = None, None  # of the last joint_states read
        self.target = None
        self.motion = JointMotion()  # the joints move (measured), from /joint_states positions
        self.answered_stamp = None  # header stamp of the last imu/data sample stepped on
        self.samples_stepped = 0  # steps on a new imu/data sample (the control rate achieved)
        self.samples_superseded = 0  # of those, stepped without a command: a newer one waited
        self.samples_t = 0.0  # when the callback stepping the samples began (krang_ros.trace)
        self.mode = None
        self.converged = None
        self.caught = 0  # the caught stand-up tries last published on ~/stand_estimate
        qos = topics.QOS

        def publisher(kind, name, private=False, profile=None):
            topic = names.private(name) if private else names.relative(name)
            return self.create_publisher(kind, topic, profile or qos[name])

        self.effort_pub = publisher(JointState, names.WHEEL_EFFORT_CMD)
        self.pose_pub = publisher(BalancedPose, names.BALANCED_POSE)
        self.diag_pub = publisher(DiagnosticArray, names.DIAGNOSTICS)
        self.mode_pub = publisher(ControllerMode, names.MODE, True, topics.LATCHED)
        self.converged_pub = publisher(Bool, names.BALANCE_CONVERGED, True, topics.LATCHED)
        self.stand_estimate_pub = publisher(StandEstimate, names.STAND_ESTIMATE, True)
        # Every imu/data sample steps the control law (the observer sees each measurement), but
        # only the newest one waiting sends a command: on_imu takes the queue (topics.STEPPED
        # keeps 50) in one wake, so a burst of samples from the bridge costs no late commands.
        # The control path's messages are taken and published as bytes (krang_ros.wire).
        self.imu_sub = self.create_subscription(
            Imu, names.relative(names.IMU), self.on_imu, topics.STEPPED, raw=True
        )
        # joint_states is read by each control step (read_joint_states), not by a callback: one
        # executor wake per sample, not two
        self.joint_sub = self.create_subscription(
            JointState,
            names.relative(names.JOINT_STATES),
            self.on_joint_states,
            topics.LATEST,
            callback_group=Polled(),
            raw=True,
        )
        self.create_subscription(
            MassModel, names.relative(names.BETA), self.on_beta, qos[names.BETA]
        )
        self.create_subscription(
            JointState, names.relative(names.POSE_TARGET), self.on_target, qos[names.POSE_TARGET]
        )
        self.create_subscription(
            DriveFault, names.relative(names.DRIVE_FAULT), self.on_drive_fault, topics.LATCHED
        )
        self.create_service(SetBool, '~/enable', self.on_enable)
        for name, call in (
            (names.HALT, self.on_halt),
            (names.CONTROLLER_RECOVER, self.on_recover),
        ):
            self.create_service(Trigger, names.private(name), call)
        self._init_actions()
        self.period = 1.0 / self.config.rate_hz
        self.last_sample_t = None
        self.timer = self.create_timer(
            self.period * (2.0 if self.step_on_imu else 1.0), self.on_timer
        )
        self.create_timer(1.0, self.publish_diagnostics)
        self.last_output = None
        self.get_logger().info(
            f'balancing at {self.config.rate_hz:.0f} Hz '
            f'({"on each imu/data sample" if self.step_on_imu else "on a timer"}), stale '
            f'timeout {self.stale_timeout} s, initial beta {beta_file or "nominal (URDF)"}'
        )

    def now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def on_imu(self, raw):
        self.on_samples([raw, *take_waiting(self.imu_sub)])

    def on_samples(self, queue):
        """Steps on each sample of `queue` (serialized /imu/data messages) in order; only the last
        step's command goes to the wheels (the others are superseded before they could act). A
        message that is not an Imu is skipped: no step on it (the stale timeout still guards), and
        the newest valid sample before it sends the command."""
        self.samples_t = trace.now() if trace.ON else 0.0
        samples = []
        for raw in queue:
            try:
                samples.append(wire.read_imu(raw))
            except wire.WireError as err:
                self._warn_imu(f'{names.IMU}: {err}; skipped')
        self.samples_superseded += max(len(samples) - 1, 0)
        now = self.now()  # the queue's arrival (one clock read: 13 us each on this machine)
        for k, sample in enumerate(samples):
            self.step_on_sample(sample, command=k == len(samples) - 1, now=now)

    def step_on_sample(self, sample, command, now):
        """One imu/data sample (a wire.ImuSample) in; a step if step_on_imu."""
        stamp = sample.stamp
        t = stamp.sec + stamp.nanosec * 1e-9
        a = sample.linear_acceleration
        self.imu = (
            now,
            pitch_from_quaternion(*sample.orientation),
            sample.angular_velocity[1],
            t,
            pitch_from_specific_force(*a, self.controller.drive.gravity),
        )
        if self.step_on_imu:
            self.timer.reset()
            self.on_tick(sample_t=t, stamp=stamp, command=command, now=now)

    def on_timer(self):
        """With step_on_imu, the watch: a step only when the newest sample is WATCH_PERIODS old,
        both by its arrival on this node's clock and by its own stamp. A step of the timer's
        would answer the next sample in its place (sim_krang's lockstep takes the first current
        frame after a sample for its answer), and in lockstep this node's /clock runs up to a
        period ahead of the sample it has, while the bridge's DMU stamps, anchored at the first
        sample's arrival, can sit a period behind the clock. After a stall of this process the
        executor runs a due timer before a waiting subscription: a sample already waiting is
        stepped on here instead of repeating the last one's stamp."""
        if self.step_on_imu:
            waiting = take_waiting(self.imu_sub)
            if waiting:
                self.on_samples(waiting)
                return
            if self.imu is not None:
                newest = max(self.imu[0], self.imu[3])
                if self.now() - newest < WATCH_PERIODS * self.period:
                    return
        self.on_tick()

    def read_joint_states(self, now=None):
        raw = take_latest(self.joint_sub)
        if raw is not None:
            self.on_joint_states(raw, now)

    def on_joint_states(self, raw, now=None):
        try:
            msg = wire.read_joint_state(raw)
        except wire.WireError as err:
            self._warn_joints(f'{names.JOINT_STATES}: {err}; ignored')
            return
        if msg.name != self._joint_names:  # the bridge's names, the same in every message
            self._joint_names, self._joint_index = msg.name, messages.name_index(msg)
        index = self._joint_index
        joints = messages.joints_from_state(msg, self.robot.pose_joints, index)
        wheels = messages.joints_from_state(msg, WHEELS, index)
        if joints is None or wheels is None:
            self._warn_joints('joint_states without all body joints and wheels; ignored')
            return
        rates = messages.velocities_from_state(msg, WHEELS, index)
        self.joint_state = (
            self.now() if now is None else now,
            joints,
            wheels,
            rates if rates is not None else np.zeros(2),
        )

    def on_target(self, msg):
        self.target = messages.joints_from_state(msg, self.robot.pose_joints)

    def on_beta(self, msg):
        values = message_values.mass_model_values(msg, self.robot.n_beta)
        if values is None:
            self.get_logger().error(f'rejected a beta of {len(msg.beta)} values or with NaN/inf')
            return
        beta = values[0]
        self.controller.set_beta(beta)
        self.get_logger().info(f'new beta (total mass {beta[0::4].sum():.2f} kg)')

    def on_drive_fault(self, msg):
        reason = message_values.drive_fault_reason(msg)
        if reason and reason != self.controller.drive_fault:
            self.get_logger().error(f'drive fault: {reason}; safe stop')
        elif not reason and self.controller.drive_fault:
            self.get_logger().info('drive fault cleared by the bridge; recover to power the loop')
        self.controller.set_drive_fault(reason)

    def sensors_stale(self, now=None):
        now = self.now() if now is None else now
        self.read_joint_states(now)
        # now == 0: on use_sim_time before the first /clock (its discovery can lag the data topics
        # by seconds under load): every age would read 0, and the first /clock would make them all
        # stale.
        return (
            now <= 0.0
            or self.imu is None
            or self.joint_state is None
            or now - self.imu[0] > self.stale_timeout
            or now - self.joint_state[0] > self.stale_timeout
        )

    def answer(self, response, reply, what):
        response.success = reply.ok
        response.message = reply.message
        self.log_reply(reply, what)
        return response

    def log_reply(self, reply, what):
        if reply.ok:  # rclpy ties a logging call site to one severity: two calls
            self.get_logger().info(f'{what}: {reply.message}')
        else:
            self.get_logger().warn(f'{what}: {reply.message}')

    def fresh(self, request):
        """The controller's answer to `request`, or a refusal while sensor data are not fresh."""
        if self.sensors_stale():
            return Reply(False, 'refused: no fresh imu/data and joint_states (is can_bridge up?)')
        return request()

    def on_enable(self, request, response):
        if request.data:
            reply = self.fresh(lambda: self.controller.request_enable(True))
        else:
            reply = self.controller.request_enable(False)
        return self.answer(response, reply, 'enable' if request.data else 'disable')

    # ---- the stand_up and sit_down actions ------------------------------------------------------
    def _init_actions(self):
        group = MutuallyExclusiveCallbackGroup()
        self.goals = {}  # goal key -> (HeldGoals, goal handle, OperatorGoal), while active
        self.actions = {
            kind: HeldGoals(
                self,
                action,
                names.private(name),
                lambda handle, kind=kind: self.on_goal(kind, handle),
                self.on_cancel,
                group,
            )
            for kind, action, name in (
                (STAND_UP, StandUp, names.STAND_UP_ACTION),
                (SIT_DOWN, SitDown, names.SIT_DOWN_ACTION),
            )
        }
        # runs only while a goal is active
        self.feedback_timer = self.create_timer(
            1.0 / FEEDBACK_HZ, self.on_feedback, callback_group=group
        )
        self.feedback_timer.cancel()

    def on_goal(self, kind, handle):
        """A goal, accepted: the controller's request, refused at once with the reason or held
        until the mode machine gets there (goals.OperatorGoal)."""
        if kind == STAND_UP:
            reply = self.fresh(self.controller.request_stand)
        else:
            reply = self.controller.request_sit()
        self.log_reply(reply, kind)
        actions = self.actions[kind]
        if not reply.ok:
            actions.end(handle, False, message=reply.message, **self.state())
            return
        self.goals[bytes(handle.goal_id.uuid)] = (actions, handle, OperatorGoal(kind, self.now()))
        if self.feedback_timer.is_canceled():
            self.feedback_timer.reset()

    def on_cancel(self, handle):
        """A stand-up is cancelled by sitting back down (on_feedback asks for it); a sit-down,
        once the controller has it, runs to the caster: cancel is refused."""
        entry = self.goals.get(bytes(handle.goal_id.uuid))
        if entry is None:
            return False  # it has ended
        if entry[2].kind != STAND_UP:
            self.get_logger().warn('cancel refused: a sit-down ends on the caster (or halt)')
            return False
        entry[2].cancel_requested = True
        return True

    def on_feedback(self):
        """FEEDBACK_HZ while a goal is active: each goal's feedback; a cancelled stand-up asks
        for the sit-down once the controller has left sit."""
        state = self.state()
        now = self.now()
        for key, (actions, handle, goal) in list(self.goals.items()):
            if goal.cancel_requested and not goal.sitting_back:
                mode = self.controller.mode.value
                if mode in ('stand_up', 'balance'):
                    reply = self.controller.request_sit()
                    self.log_reply(reply, 'stand_up cancel: sit_down')
                    if reply.ok:
                        goal.sitting_back = True
                    else:
                        why = f'cancelled, not sitting back down ({reply.message}): standing up'
                        self.end_goal(key, False, why, True)
                        continue
            actions.feedback(handle, elapsed=now - goal.started, **state)

    def judge_goals(self, out):
        """After a control step with events: end the goals it decides."""
        for key, (_, _, goal) in list(self.goals.items()):
            ending = goal.after_step(out.mode, out.events)
            if ending is not None:
                self.end_goal(key, ending.success, ending.message, ending.cancelled)

    def end_goal(self, key, success, message, cancelled=False):
        actions, handle, goal = self.goals.pop(key)
        actions.end(handle, success, cancelled, message=message, **self.state())
        self.log_reply(Reply(success, message), f'{goal.kind} goal')
        if not self.goals:
            self.feedback_timer.cancel()

    def state(self):
        """The mode and base pitch an action's feedback and result report."""
        pitch = self.imu[1] if self.imu is not None else float('nan')
        return {'mode': MODE_CODES[self.controller.mode.value], 'base_pitch': pitch}

    def on_halt(self, request, response):
        return self.answer(response, self.controller.request_stop('operator halt'), 'halt')

    def on_recover(self, request, response):
        return self.answer(response, self.fresh(self.controller.recover), 'recover')

    def on_tick(self, sample_t=None, stamp=None, command=True, now=None):
        """One control step. `sample_t`: the time of the IMU sample that triggered it (its header
        stamp, the sample's time at the bridge), so the ESO integrates over the samples' own
        spacing; `stamp`: that header stamp, which the wheel command carries back; `command`:
        publish the wheel command (not for a sample a newer one already supersedes); `now`: this
        node's clock, if the caller has read it."""
        now = self.now() if now is None else now
        stale = self.sensors_stale(now)
        if sample_t is None:
            sample_t = now
        if (
            self.last_sample_t is not None and sample_t <= self.last_sample_t
        ):  # a repeated or older stamp
            sample_t = max(now, self.last_sample_t + self.period)
        self.last_sample_t = sample_t
        if self.imu is None or self.joint_state is None:
            sample = ControlSample(
                sample_t,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
                np.zeros(len(self.robot.pose_joints)),
                False,
            )
        else:
            _, q_base, pitch_rate, _, gravity_pitch = self.imu
            _, joints, wheels, rates = self.joint_state
            # a move pending (the pose server's target not reached, paused or not) is not the
            # joints moving: the observer's hold follows the joints, the detector waits for both
            pending = self.target is not None and bool(np.any(np.abs(self.target - joints) > 0.01))
            sample = ControlSample(
                sample_t,
                q_base,
                pitch_rate,
                wheels[0],
                wheels[1],
                rates[0],
                rates[1],
                joints,
                self.motion.update(self.joint_state[0], joints),
                pending,
                gravity_pitch,
            )
        out = self.controller.step(sample, stale=stale)
        self.last_output = out
        # stamped with the sample it answers (sim_krang's lockstep, latency measurements); a
        # timer step answers no new sample and repeats the last sample's stamp
        if stamp is not None:
            self.answered_stamp = stamp
            self.samples_stepped += 1
        if command:
            self.effort_pub.publish(
                messages.wheel_effort(
                    self.answered_stamp or self.get_clock().now().to_msg(),
                    WHEELS,
                    (out.torque_left, out.torque_right),
                )
            )
            if trace.ON and stamp is not None:
                trace.record('step', stamp, self.samples_t, trace.now())
        for event in out.events:
            self.get_logger().info(event)
        mode_stamp = None
        if out.mode != self.mode:
            self.get_logger().info(f'mode {self.mode} -> {out.mode}')
            self.mode = out.mode
            mode_stamp = self.get_clock().now().to_msg()
            self.mode_pub.publish(messages.controller_mode(mode_stamp, out.mode))
            self.publish_diagnostics()  # a mode change at once, not at the next 1 Hz report
        estimate = self.controller.stand_estimate()
        if (0 if estimate is None else estimate[0]) != self.caught:
            self.publish_stand_estimate(estimate, mode_stamp)
        if out.events and self.goals:  # every mode change has its event
            self.judge_goals(out)
        if out.balance_converged != self.converged:
            self.converged = out.balance_converged
            self.converged_pub.publish(Bool(data=out.balance_converged))
        if out.move_points:
            stamp = self.get_clock().now().to_msg()
            for point in out.move_points:
                self.pose_pub.publish(messages.balanced_pose(stamp, self.robot.pose_joints, point))
            self.get_logger().info(
                f'{len(out.move_points)} points read on the move: balance pitch '
                + ', '.join(f'{p.q_base:+.4f}' for p in out.move_points)
                + ' rad'
            )
        if out.balanced_point is not None:
            point = out.balanced_point
            self.pose_pub.publish(
                messages.balanced_pose(
                    self.get_clock().now().to_msg(), self.robot.pose_joints, point
                )
            )
            self.get_logger().info(
                f'balanced pose detected: q_base {point.q_base:+.4f} rad '
                f'(standard error {point.q_base_se:.5f}; the IMU filter: '
                f'{point.q_base_filter:+.4f})'
            )

    def publish_stand_estimate(self, estimate, stamp):
        """A new catch (tries since the last BALANCE went up) on ~/stand_estimate, stamped as the
        step's mode change (`stamp`, None if none): the pose server acts on an estimate no older
        than the controller's mode. None (BALANCE reached, or the tries granted again) only
        resets the count."""
        self.caught = 0 if estimate is None else estimate[0]
        if estimate is None:
            return
        tries, error = estimate
        ctl = self.controller
        tries_max = ctl.stand.tries_max
        window = (ctl.modes.stand_error_min, ctl.modes.stand_error_max)
        self.stand_estimate_pub.publish(
            messages.stand_estimate(
                stamp or self.get_clock().now().to_msg(), tries, tries_max, error, window
            )
        )
        self.get_logger().info(
            f'stand-up caught (try {tries} of {tries_max}): CoM-angle error estimate '
            f'{error:+.4f} rad, published on {names.private(names.STAND_ESTIMATE)}'
        )

    def publish_diagnostics(self):
        out = self.last_output
        level = 'ok' if out is not None and out.mode != 'safe_stop' else 'warn'
        values = (
            {}
            if out is None
            else {
                'mode': out.mode,
                'theta_rad': f'{out.theta:+.4f}',
                'x_m': f'{out.x:+.3f}',
                'f_hat_theta': f'{out.f_hat_theta:+.3f}',
                'f_hat_x': f'{out.f_hat_x:+.3f}',
                'x_ref_m': f'{out.x_ref:+.3f}',
                'balance_trim_rad': f'{out.balance_trim:+.4f}',
                'balance_converged': str(out.balance_converged),
            }
        )
        values['samples_stepped'] = self.samples_stepped
        values['samples_superseded'] = self.samples_superseded
        if self.controller.drive_fault:
            values['drive_fault'] = self.controller.drive_fault
        self.diag_pub.publish(
            messages.diagnostics(
                self.get_clock().now().to_msg(),
                'adrc_controller',
                level,
                f'mode {out.mode if out else "starting"}',
                values,
            )
        )


def main(args=None):
    return run_node(AdrcControllerNode, args)


if __name__ == '__main__':
    sys.exit(main())
