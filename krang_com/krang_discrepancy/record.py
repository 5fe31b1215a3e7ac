"""The measured-data record of `krang discrepancy`: one run on a uniform clock, and the alignment.

``Record``: one run on a uniform measurement clock (base pitch, pitch rate, wheel encoder angle and
rate relative to the body, body joints) plus the commanded wheel torques at their own times (a
zero-order hold: what the drives were asked for, in N m at the wheels). loaders.py makes records
from files, synthetic.py from sessions of the simulated robot.

Alignment
    Measured channels are linearly resampled to one uniform clock (the median sample period of the
    source, or ``rate_hz``). Commands stay a step function on their own clock: the replay
    integrates its exact average over each integration sub-step, so a 500 Hz command stream
    replayed on a 200 Hz measurement grid loses nothing, and a fractional actuation delay is a
    smooth parameter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from krang_model.drivetrain import HeldCommand

CHANNELS = ('q_base', 'pitch_rate', 'wheel', 'wheel_rate')
CHANNEL_UNITS = ('rad', 'rad/s', 'rad', 'rad/s')


@dataclass
class Record:
    """One measured run. Measurement arrays share the uniform clock ``t`` (s).

    q_base        IMU pitch (rad; krang_model/README.md, Conventions)
    pitch_rate    IMU pitch rate (rad/s)
    wheel         mean wheel encoder angle RELATIVE TO THE BODY (rad); ground-referenced angle
                  phi = wheel + q_base (the hardware's x_wheel_rad)
    wheel_rate    its rate (rad/s)
    joints        (N, 16) body joints in pose order (rad)
    cmd_t, cmd_torque   command times (s) and commanded wheel torques (M, 2) [left, right], N m at
                  the wheels, each held until the next command (zero before the first)
    torque_limit  N m per wheel where the drives clamp (current limit x Kt x gear)
    """

    t: np.ndarray
    q_base: np.ndarray
    pitch_rate: np.ndarray
    wheel: np.ndarray
    wheel_rate: np.ndarray
    joints: np.ndarray
    cmd_t: np.ndarray
    cmd_torque: np.ndarray
    torque_limit: float = math.inf
    name: str = ''
    source: str = ''
    kind: str = ''
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.t = np.asarray(self.t, float)
        n = self.t.size
        for k in ('q_base', 'pitch_rate', 'wheel', 'wheel_rate'):
            v = np.asarray(getattr(self, k), float).ravel()
            if v.size != n:
                raise ValueError(f'{k}: {v.size} samples, t has {n}')
            setattr(self, k, v)
        self.joints = np.atleast_2d(np.asarray(self.joints, float))
        if self.joints.shape[0] != n:
            raise ValueError(f'joints: {self.joints.shape[0]} rows, t has {n}')
        self.cmd_t = np.asarray(self.cmd_t, float).ravel()
        self.cmd_torque = np.asarray(self.cmd_torque, float).reshape(-1, 2)
        if self.cmd_torque.shape[0] != self.cmd_t.size:
            raise ValueError('cmd_t and cmd_torque differ in length')
        if n < 3:
            raise ValueError('a record needs at least three samples')

    def __len__(self):
        return self.t.size

    @property
    def period(self) -> float:
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def phi(self):
        return self.wheel + self.q_base

    def command_at(self, t):
        """Commanded wheel torques (len(t), 2) at times t, held as the drives hold them
        (``krang_model.drivetrain.HeldCommand``)."""
        return HeldCommand(self.cmd_t, np.reshape(self.cmd_torque, (-1, 2))).applied(t)

    def total_torque_at(self, t):
        lim = self.torque_limit
        c = np.clip(self.command_at(t), -lim, lim)
        return c.sum(axis=1)

    def slice(self, t0: float, t1: float) -> 'Record':
        """The part of the record between t0 and t1 (s, on its own clock)."""
        m = (self.t >= t0) & (self.t <= t1)
        mc = (self.cmd_t >= t0 - 1.0) & (self.cmd_t <= t1)
        return replace(
            self,
            t=self.t[m],
            q_base=self.q_base[m],
            pitch_rate=self.pitch_rate[m],
            wheel=self.wheel[m],
            wheel_rate=self.wheel_rate[m],
            joints=self.joints[m],
            cmd_t=self.cmd_t[mc],
            cmd_torque=self.cmd_torque[mc],
            meta=dict(self.meta),
        )


def uniform_clock(t, rate_hz=None):
    """A uniform grid over [t0, t1] at rate_hz (default: the median sample rate of t)."""
    t = np.asarray(t, float)
    period = 1.0 / rate_hz if rate_hz else float(np.median(np.diff(t)))
    if not period > 0:
        raise ValueError('cannot build a clock: non-increasing times')
    n = int(math.floor((t[-1] - t[0]) / period + 1e-9)) + 1
    return t[0] + period * np.arange(n)


def resample(t_src, y_src, t_new):
    """Linear interpolation of y_src (N,) or (N, K) at t_new."""
    y = np.asarray(y_src, float)
    if y.ndim == 1:
        return np.interp(t_new, t_src, y)
    return np.column_stack([np.interp(t_new, t_src, y[:, k]) for k in range(y.shape[1])])
