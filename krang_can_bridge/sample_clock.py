"""Times of a fixed-rate sensor's samples from their sequence counter, not from their arrival.

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
