"""Action servers for the robot's long requests (stand up, sit down, the move to the next pose).

A goal is accepted at once and then held: the node works on it from its own callbacks (the mode
machine, the move's stream) and executes the goal only to end it, with its result. An execute
callback that awaited the outcome instead would be a task in progress for the whole request,
and while one is, the executor (krang_ros.executor) rebuilds its wait set at every wake, the
control path's included. So a goal's status reads ACCEPTED while the node works on it, then
SUCCEEDED, ABORTED or CANCELED.

A refused goal is accepted and ended at once as ABORTED: its result says why (a rejected goal
carries no message)."""

from rclpy.action import ActionServer, CancelResponse, GoalResponse


def goal_key(goal_handle):
    return bytes(goal_handle.goal_id.uuid)


class HeldGoals:
    """An ActionServer of `action_type` at `name`: `on_goal(goal_handle)` takes each accepted goal
    (and must end it, now or later, with `end`); `on_cancel(goal_handle)` answers a cancel
    request with True (accepted: the node ends the goal when it has stopped) or False."""

    def __init__(self, node, action_type, name, on_goal, on_cancel, callback_group):
        self.action_type = action_type
        self._endings = {}  # goal key -> (how, result) until the goal is executed to end
        self.server = ActionServer(
            node,
            action_type,
            name,
            execute_callback=self._conclude,
            goal_callback=lambda goal: GoalResponse.ACCEPT,
            handle_accepted_callback=on_goal,
            cancel_callback=lambda handle: (
                CancelResponse.ACCEPT if on_cancel(handle) else CancelResponse.REJECT
            ),
            callback_group=callback_group,
        )

    def feedback(self, goal_handle, **fields):
        goal_handle.publish_feedback(self.action_type.Feedback(**fields))

    def end(self, goal_handle, success, cancelled=False, **fields):
        """End the goal with a result of `fields` (success included): CANCELED if `cancelled`
        and a cancel was requested, else SUCCEEDED or ABORTED by `success`."""
        how = 'canceled' if cancelled and goal_handle.is_cancel_requested else None
        how = how or ('succeeded' if success else 'aborted')
        self._endings[goal_key(goal_handle)] = (
            how,
            self.action_type.Result(success=success, **fields),
        )
        goal_handle.execute()

    def _conclude(self, goal_handle):
        how, result = self._endings.pop(goal_key(goal_handle))
        if how == 'canceled':
            goal_handle.canceled()
        elif how == 'succeeded':
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result

    def destroy(self):
        self.server.destroy()
