"""The body resting on its caster, from the IMU pitch: the rule of BALANCE's caster catch and of
the stand-up's (stand.py).

The pitch is low-passed over ``FILTER_S`` before it is compared with the contact limit (the
caster's contact pitch plus ``safety.caster_margin_rad``, 3 mrad). The IMU's pitch scatters by
+-3 mrad from sample to sample, as much as the margin: with the raw pitch, a body resting on its
caster 0.5 mrad above the modelled contact (MuJoCo's) crossed the limit every few samples, each
crossing restarted the 0.1 s hold, and a caught stand-up went on being pushed along its caster at
49 A for 0.8 s more (truth 7500, to 2.2 m/s). Filtered, the scatter is about a fifth, for 20 ms
of delay.
"""

from __future__ import annotations

import math

#: the low-pass time constant of the pitch the rule compares, s
FILTER_S = 0.02


class CasterContact:
    """``update(t, pitch)`` is True once the low-passed pitch has stayed below `limit` for
    `hold_s` (and on every later step until it rises or ``reset``)."""

    def __init__(self, limit: float, hold_s: float):
        self.limit = limit
        self.hold_s = hold_s
        self.reset()

    def reset(self) -> None:
        self._lp: tuple[float, float] | None = None  # (t, low-passed pitch)
        self._since: float | None = None

    @property
    def pitch(self) -> float:
        """The low-passed pitch (NaN before the first sample)."""
        return math.nan if self._lp is None else self._lp[1]

    def update(self, t: float, pitch: float) -> bool:
        if self._lp is None or not 0.0 < t - self._lp[0] < 1.0:
            q = pitch
        else:
            t0, q = self._lp
            q += (1.0 - math.exp(-(t - t0) / FILTER_S)) * (pitch - q)
        self._lp = (t, q)
        if q >= self.limit:
            self._since = None
            return False
        if self._since is None:
            self._since = t
        return t - self._since >= self.hold_s
