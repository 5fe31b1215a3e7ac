"""The control path's processes under SCHED_FIFO: the `thread_priority` parameter of can_bridge
and adrc_controller.

On a robot computer that does other work, a control process on the default scheduler waits for a
CPU behind whatever else is runnable; under SCHED_FIFO it preempts every such process at once.
ros2_control's controller_manager does the same for its update thread (its `thread_priority`,
50). Here it is the whole process, every thread: a Python node's threads share one GIL, and a
receive thread on the default scheduler holding it would stall a real-time executor thread behind
it (priority inversion). Threads started later inherit the policy from the thread that starts
them. The kernel's real-time throttling (95 % of each second by default) keeps a runaway node
from locking a core. Where it is refused (no CAP_SYS_NICE and an rtprio limit below the priority)
the node logs one warning and runs on the default scheduler, as controller_manager does.
"""

import os
from dataclasses import dataclass, field

from .params import declare

MAX_PRIORITY = 99  # SCHED_FIFO priorities are 1..99 (sched(7))


@dataclass(frozen=True)
class SchedulingParams:
    """The parameter, declared by each node of the control path (krang_ros.params)."""

    thread_priority: int = field(
        default=0,
        metadata={
            'doc': 'SCHED_FIFO priority of every thread of the process, 1-99 (needs CAP_SYS_NICE '
            'or an rtprio limit; refused: a warning, the default scheduler); 0: the default '
            'scheduler'
        },
    )

    def __post_init__(self):
        if not 0 <= self.thread_priority <= MAX_PRIORITY:
            raise ValueError(
                f'thread_priority must be 0 (the default scheduler) to {MAX_PRIORITY}, '
                f'got {self.thread_priority!r}'
            )


def set_fifo_priority(priority: int) -> None:
    """Every thread of this process under SCHED_FIFO at `priority`. OSError when refused (then
    the first thread already refuses, and nothing changed)."""
    param = os.sched_param(priority)
    for tid in sorted(int(t) for t in os.listdir('/proc/self/task')):
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, param)
        except ProcessLookupError:
            pass  # the thread ended meanwhile


def declare_thread_priority(node) -> int:
    """Declare `thread_priority` on `node` and apply it; returns the priority in effect (0 on the
    default scheduler)."""
    priority = declare(node, SchedulingParams).thread_priority
    if priority == 0:
        return 0
    try:
        set_fifo_priority(priority)
    except OSError as exc:
        node.get_logger().warning(
            f'thread_priority {priority} refused ({exc.strerror}): running on the default '
            'scheduler; grant an rtprio limit (README, "Running on the robot")'
        )
        return 0
    node.get_logger().info(f'every thread under SCHED_FIFO priority {priority}')
    return priority
