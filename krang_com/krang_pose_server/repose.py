"""The pose server's re-pose after a caught stand-up (a part of node.PoseServer; it reads
messages by their fields and imports no ROS package).

A stand-up that falls back on its caster is caught by the controller, which publishes its
estimate of the CoM-angle error on its latched stand_estimate and retries once the robot rests
and the joints have reached the pose server's target. Before that retry the waist moves so that
the CoM, corrected by the estimate, lies where the stand pose meant it to
(stand_pose.restand_pose): a CoM only a few mrad behind the axle on the caster can neither
balance clear of the caster nor brake the rolling robot.
"""

from .stand_pose import restand_pose


def _time(stamp):
    """A header stamp's (sec, nanosec), ordered as the times."""
    return stamp.sec, stamp.nanosec


class ReposeAfterCaughtStand:
    """PoseServer's handling of the controller's StandEstimate. Uses the node's mode and
    mode_stamp (its latched mode topic), posterior, move, goal, arm_fault, measured_joints and
    begin_move."""

    def on_stand_estimate(self, msg):
        self.stand_estimate = msg
        self.repose_if_due()

    def repose_if_due(self):
        """The re-pose, once per estimate: while the controller sits since the catch (its mode
        message no newer than the estimate: the controller stamps both with the catch's step),
        no move is under way and no arm fault is latched. An estimate that arrives before the
        sit, or before the first /joint_states, waits for them (stream_move asks again); one
        older than the sit (a pose server started long after the catch, the robot since
        balanced and sat down) is dropped."""
        msg = self.stand_estimate
        if msg is None or self.mode != 'sit':
            return
        joints = self.measured_joints()
        if joints is None:
            return
        self.stand_estimate = None
        error, log = msg.com_angle_error, self.get_logger()
        if _time(msg.header.stamp) < _time(self.mode_stamp):
            log.info(f'no re-pose: the stand estimate ({error:+.4f} rad) predates the sit')
            return
        why = None
        if self.move is not None or self.goal is not None:
            why = 'a move is under way'
        elif self.arm_fault:
            why = self.arm_refusal()
        if why is not None:
            log.warning(f'no re-pose after a caught stand-up: {why}')
            return
        beta = self.robot.nominal_beta if self.posterior is None else self.posterior[0]
        window = (msg.stand_window_min, msg.stand_window_max)
        pose = restand_pose(self.robot, beta, joints, error, window)
        if pose is None:
            log.info(
                'no re-pose needed after a caught stand-up (CoM-angle error estimate '
                f'{error:+.4f} rad)'
            )
            return
        log.info(
            f're-posing the waist {joints[0]:.3f} -> {pose[0]:.3f} rad after a caught stand-up '
            f'(CoM-angle error estimate {error:+.4f} rad)'
        )
        self.begin_move(joints, pose, reposing=True)
