"""Streaming a pose move that waits for the controller's balance estimate.

The pose server streams a StraightLineMove as joint targets. While the controller reports an
unconverged balance estimate (``/adrc_controller/balance_converged`` false: the robot does not
keep its place while the joints move, or the balance-point observer has not settled at rest) the
setpoint holds where it is, so the joints stop and the observer can re-converge at the pose
reached so far; it resumes when the flag returns. The pauses of one move add up to at most
``max_pause_s``; after that the rest of the move runs at ``slow_fraction`` of its planned speed
whatever the flag says, so every move ends (within duration / slow_fraction + max_pause_s).

Plain numpy: the pose server node and the offline closed loop (krang_sim.closed_loop) both step
this one object.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sequence import StraightLineMove


#: seconds: sums of stream periods are not exact
_EPS = 1e-9


@dataclass(frozen=True)
class PauseConfig:
    """How a move waits for the controller (pose_server parameters ``max_pause_s``,
    ``slow_fraction``)."""

    max_pause_s: float = 20.0
    slow_fraction: float = 0.5

    def __post_init__(self):
        if self.max_pause_s < 0 or not 0 < self.slow_fraction <= 1:
            raise ValueError(
                f'max_pause_s must be >= 0 and slow_fraction in (0, 1], got '
                f'{self.max_pause_s} and {self.slow_fraction}'
            )


class MoveStreamer:
    """Progress along one move. ``advance(dt, converged)`` once per streamed target, then
    ``setpoint`` is the target to send; ``done`` once the goal has been sent."""

    def __init__(self, move: StraightLineMove, config: PauseConfig = PauseConfig()):
        self.move = move
        self.config = config
        self.progress_s = 0.0  # time along the planned path
        self.paused_s = 0.0  # total held time of this move
        self.pauses = 0
        self.paused = False
        self.slow = False  # the pause budget is spent: the rest at slow_fraction

    @property
    def setpoint(self) -> np.ndarray:
        return self.move.at(self.progress_s)

    @property
    def done(self) -> bool:
        return self.progress_s >= self.move.duration - _EPS

    def advance(self, dt: float, converged: bool) -> str | None:
        """Move the setpoint on by `dt` of wall time given the controller's flag; returns an event
        ('pause', 'resume', 'slow': the budget is spent) or None."""
        event = None
        if not converged and not self.slow:
            budget = self.config.max_pause_s - self.paused_s
            if budget > _EPS:
                held = min(dt, budget)
                self.paused_s += held
                dt -= held
                if not self.paused:
                    self.paused = True
                    self.pauses += 1
                    event = 'pause'
            if dt > _EPS or self.paused_s >= self.config.max_pause_s - _EPS:
                self.slow = True
                self.paused = False
                event = 'slow'
        elif self.paused:
            self.paused = False
            event = 'resume'
        rate = self.config.slow_fraction if self.slow else 1.0
        self.progress_s = min(self.progress_s + rate * max(dt, 0.0), self.move.duration)
        return event

    def summary(self) -> str:
        text = f'{self.pauses} pause(s), {self.paused_s:.1f} s paused'
        if self.slow:
            text += f'; the rest at {self.config.slow_fraction:g} of the speed'
        return text
