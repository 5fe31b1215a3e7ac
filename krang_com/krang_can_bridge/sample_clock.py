"""The bridge's times: the devices' time base (TimeBase), and the times of a fixed-rate sensor's
samples from their sequence counter, not from their arrival (SampleClock).

The DMU streams at a fixed rate and numbers its samples (8 bits). Timing them by arrival goes wrong
after a stall of the receiving process: a burst of queued samples arrives at once, and the IMU
filter integrated the last gyro rate over the whole gap (0.02 rad of pitch error after one pose
move at load 12 on 2 cores, which the slow accelerometer correction then took ~30 s to walk off).
By the counter, each sample is one period after the previous one. The estimate is kept near the
receiver's clock: at most `lag_max_s` behind it (the clock jumped past a queue of frames, or the
track started late) and re-anchored when more than `lead_max_s` ahead (a sensor restart, or the
track lost).
"""

from __future__ import annotations

import time
from typing import Callable

SIM_TIME_SLACK_S = 0.025  # simulated time: checks run at most this far past the newest frame


class TimeBase:
    """The devices' time, which every time of the core is in (IMU filter steps, silence and
    command timeouts), and the stamps' offset from it.

    Wall time (monotonic) on the robot. In simulation (`sim_clock`, seconds of the simulator's
    clock), the simulator's time, because a simulated DMU samples in simulated time: a simulator
    starved of CPU runs slower than the wall clock, and integrating its gyro over wall-clock gaps
    overstates every pitch change by the slow-down. That clock may reach the process on another
    path than the frames, and after a stall run ahead of frames still queued in the sockets; so
    received frames are stamped with it, but the checks run at most SIM_TIME_SLACK_S past the
    newest frame stamped: a device silent while others talk is still caught, and when the
    simulator stops, its clock stops too.

    Stamps are the device time as wall time (one offset fixed at start, so the spacing of the
    samples stays the devices'), or the simulator's time as it is."""

    def __init__(self, sim_clock: Callable[[], float] | None = None):
        self.simulated = sim_clock is not None
        self.frame_time = sim_clock if sim_clock is not None else time.monotonic
        self.newest_frame = self.frame_time()
        self.stamp_offset = 0.0 if self.simulated else time.time() - time.monotonic()

    def known(self) -> bool:
        """Whether the devices' time exists yet: always on the robot; in simulation once the
        simulator's clock reached this process (ROS time 0 means no /clock message yet). A frame
        stamped before that would be stamped 0, and the clock's first reading, the simulator's
        time since it started, would then make every device heard so far look silent since
        (an arm fault for every PowerCube module at start-up, under load)."""
        return not self.simulated or self.frame_time() > 0.0

    def device_time(self) -> float:
        if not self.simulated:
            return self.frame_time()
        return min(self.frame_time(), self.newest_frame + SIM_TIME_SLACK_S)

    def frame_seen(self, t: float) -> None:
        if t > self.newest_frame:
            self.newest_frame = t

    def stamp_seconds(self, t: float) -> float:
        return t + self.stamp_offset


class SampleClock:
    def __init__(
        self, period_s: float, lag_max_s: float = 0.04, lead_max_s: float = 1.0, modulo: int = 256
    ):
        if period_s <= 0 or lag_max_s < 0 or lead_max_s <= 0:
            raise ValueError('period_s and lead_max_s must be positive, lag_max_s not negative')
        self.period = float(period_s)
        self.lag_max = float(lag_max_s)
        self.lead_max = float(lead_max_s)
        self.modulo = int(modulo)
        self._last = None  # (sequence, time) of the last sample

    def time_of(self, sequence: int, now: float) -> float:
        """The time of the sample numbered `sequence`, received at `now` (the same number twice:
        the same time,
        as for the DMU's rate and acceleration frames of one sample)."""
        t = now
        if self._last is not None:
            seq, t_last = self._last
            t = t_last + ((sequence - seq) % self.modulo) * self.period
            if t > now + self.lead_max:
                t = now
            elif t < now - self.lag_max:
                t = now - self.lag_max
        self._last = (sequence, t)
        return t
