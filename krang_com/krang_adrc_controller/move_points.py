"""Points read while the joints move: the balance-point observer's estimate of where the robot
balances, averaged over short windows of a move.

A balanced pose at rest gives one number for 92 parameters; a move passes through balanced
configurations all the way. The pitch itself is no reading of them while the arms move (several
mrad off the balance pitch: the controller leans to carry the robot along), but the controller's
balance-point observer models that lean: its raw estimate of the CoM-angle error, minus the model's
CoM offset at the joints of that moment, is its estimate of the true balance pitch, every step.
Noisy step by step (several mrad), it is within about 1 mrad averaged over a second in the
offline closed loop, except where the arms accelerate (the start of a move) and decelerate (its
end), whose reaction the reduced model does not hold. Averaged over a second it is 0.7-2.2 mrad
rms off offline and 1.5-2.3 mrad over the simulated node set (docs/learning.md, "Points read while
moving").

``MovePoints`` collects those estimates and the measured joints in bins of ``BIN_S`` while a move
is under way, and when the move ends gives ``per_move`` points: window means of ``window_s``,
spread evenly over the stretches of steady motion. A stretch is a run of bins in each of which
the joints moved (a bin in which they never did is a pause; a stop of a few tens of ms at each
streamed setpoint is not); its windows start ``head_s`` after it starts and end ``tail_s`` before
it ends. A move the pose server pauses is several stretches: the arms stop and start again inside
it, and a window across a stop held their reaction (15.8 mrad off in the offline closed loop).
Each is a ``BalancedPoint`` with ``in_motion`` set and ``sigma_rad`` as its standard error, so the
learner weighs it below a point at rest. A move too short for one window gives none. The bins keep
the cost per control step to a few additions and the work at the move's end to a few hundred bins.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .detector import BalancedPoint

#: the width of the bins the estimates are summed in, s (a window is a whole number of them)
BIN_S = 0.1
#: a window needs at least this share of its bins' samples (a starved control loop skips some)
MIN_COVERAGE = 0.5
#: the longest move kept, s: past it the move's later samples are not collected
MAX_MOVE_S = 600.0


@dataclass(frozen=True)
class MovePointConfig:
    """Points read while moving (parameters ``move_points.*``); off with ``per_move`` 0."""

    per_move: int = field(
        default=3, metadata={'doc': 'points read on each move, >= 0 (0 = none: rest points only)'}
    )
    window_s: float = field(
        default=1.0, metadata={'doc': "each point's averaging window, s (a multiple of 0.1)"}
    )
    head_s: float = field(
        default=2.0,
        metadata={
            'doc': 'no window starts within this of the start of a stretch of steady motion, s '
            '(the arms accelerate)'
        },
    )
    tail_s: float = field(
        default=1.0,
        metadata={'doc': 'no window ends within this of its end, s (they decelerate)'},
    )
    sigma_rad: float = field(
        default=1e-3,
        metadata={'doc': "each point's standard error for the learner, rad (> 0)"},
    )

    def __post_init__(self):
        if self.per_move < 0 or self.window_s < BIN_S or self.head_s < 0 or self.tail_s < 0:
            raise ValueError(
                'move_points: per_move >= 0, window_s >= 0.1, head_s and tail_s >= 0 needed'
            )
        if not self.sigma_rad > 0:
            raise ValueError('move_points.sigma_rad must be > 0')


class MovePoints:
    """Bins of one move's balance-pitch estimates and joints (see the module docstring)."""

    def __init__(self, config: MovePointConfig = MovePointConfig()):
        self.config = config
        self.enabled = config.per_move > 0
        self._width = max(1, round(config.window_s / BIN_S))  # bins per window
        self.reset()

    def reset(self) -> None:
        """Forget the move under way (the robot left BALANCE, or the move was abandoned)."""
        self._t0 = None  # the move's first sample
        self._t_last = None
        self._bin = -1
        self._sums = []  # per bin: [sum of estimates, sum of squares, count]
        self._joints = []  # per bin: sum of joints
        self._moved = []  # per bin: the joints moved at one of its samples at least

    @property
    def active(self) -> bool:
        """A move is being collected."""
        return self._t0 is not None

    def add(self, t: float, balance_pitch: float, joints, moving: bool = True) -> None:
        """One control step of a move: the estimated balance pitch (rad), the measured joints,
        whether they move (False: the move is pending but the joints are still)."""
        if self._t0 is None:
            self._t0 = t
        if t - self._t0 > MAX_MOVE_S or not balance_pitch == balance_pitch:
            return
        self._t_last = t
        k = int((t - self._t0) / BIN_S)
        while self._bin < k:
            self._sums.append([0.0, 0.0, 0])
            self._joints.append(np.zeros(len(joints)))
            self._moved.append(False)
            self._bin += 1
        if moving:
            self._moved[k] = True
        s = self._sums[k]
        s[0] += balance_pitch
        s[1] += balance_pitch * balance_pitch
        s[2] += 1
        self._joints[k] += joints

    def end(self) -> list[BalancedPoint]:
        """The move ended: its points (possibly none), and the collection starts afresh."""
        points = self._points() if self.enabled and self._t0 is not None else []
        self.reset()
        return points

    def _window_starts(self) -> list[int]:
        """The first bins of the windows that fit the stretches of steady motion (see the module
        docstring), in order."""
        c, w = self.config, self._width
        head = int(np.ceil(c.head_s / BIN_S - 1e-9))
        tail = int(np.ceil(c.tail_s / BIN_S - 1e-9))
        end = int((self._t_last - self._t0) / BIN_S + 1e-9)  # one past the move's last full bin
        starts, first = [], 0
        for b in range(end + 1):
            if b == end or (self._sums[b][2] and not self._moved[b]):  # a bin of a pause
                starts += range(first + head, b - tail - w + 1)
                first = b + 1
        return starts

    def _points(self) -> list[BalancedPoint]:
        c, w = self.config, self._width
        candidates = self._window_starts()
        if not candidates:
            return []
        counts = np.array([s[2] for s in self._sums], float)
        per_bin = np.median(counts[counts > 0]) if np.any(counts > 0) else 0.0
        picks = np.round(np.linspace(0, len(candidates) - 1, c.per_move)).astype(int)
        points = []
        for b in dict.fromkeys(candidates[i] for i in picks.tolist()):
            sums = self._sums[b : b + w]
            n = sum(s[2] for s in sums)
            if n == 0 or n < MIN_COVERAGE * per_bin * w:
                continue
            mean = sum(s[0] for s in sums) / n
            var = max(0.0, sum(s[1] for s in sums) / n - mean * mean)
            points.append(
                BalancedPoint(
                    t=self._t0 + (b + w) * BIN_S,
                    q_base=mean,
                    joints=np.sum(self._joints[b : b + w], axis=0) / n,
                    q_base_std=float(np.sqrt(var)),
                    n_samples=int(n),
                    window_s=w * BIN_S,
                    q_base_se=c.sigma_rad,
                    in_motion=True,
                )
            )
        return points
