"""Phase labels of a record (sitting, standing up, balancing, moving joints, sitting down) from
the measurements alone: the hardware logs have no mode column."""

from __future__ import annotations

import numpy as np

from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang

from .record import Record

PHASES = ('sitting', 'standing_up', 'balancing', 'moving_joints', 'sitting_down')


def label_phases(
    rec: Record,
    caster_pitch: float | None = None,
    *,
    sit_band=0.015,
    still_rate=0.1,
    still_s=0.5,
    joint_rate=0.02,
) -> np.ndarray:
    """Phase of every sample (strings of PHASES), from the measurements alone (the hardware logs
    have no mode column):

    * sitting: q_base on the record's low plateau (within ``sit_band`` of its 1st percentile) when
      that plateau is near the caster pitch (within 0.08 rad; an IMU bias moves it);
    * standing_up: from leaving the plateau until |pitch rate| < ``still_rate`` for ``still_s``;
    * sitting_down: from the last such quiet spell to the plateau;
    * moving_joints: otherwise, while any body joint moves faster than ``joint_rate`` rad/s;
    * balancing: the rest.

    `caster_pitch` defaults to the drive train's (krang_model.drivetrain).
    """
    if caster_pitch is None:
        caster_pitch = drivetrain(load_krang()).caster_pitch
    n = len(rec)
    labels = np.full(n, 'balancing', dtype=object)
    q = rec.q_base
    low = float(np.percentile(q, 1))
    sitting = np.zeros(n, bool)
    if low < caster_pitch + 0.08:
        sitting = q < low + sit_band
    dt = rec.period
    w = max(1, int(round(still_s / dt)))
    calm = np.abs(rec.pitch_rate) < still_rate
    # calm_run[i]: samples i-w+1..i all calm
    cs = np.concatenate([[0], np.cumsum(calm)])
    calm_run = np.zeros(n, bool)
    calm_run[w - 1 :] = (cs[w:] - cs[:-w]) == w
    # joint motion (smoothed over 0.1 s)
    k = max(1, int(round(0.1 / dt)))
    jd = np.abs(rec.joints[k:] - rec.joints[:-k]).max(axis=1) / (k * dt) if n > k else np.zeros(0)
    moving = np.zeros(n, bool)
    moving[k // 2 : k // 2 + jd.size] = jd > joint_rate
    i = 0
    while i < n:
        if sitting[i]:
            labels[i] = 'sitting'
            i += 1
            continue
        j = i
        while j < n and not sitting[j]:
            j += 1
        # non-sitting stretch [i, j)
        stretch = np.arange(i, j)
        if i > 0:  # came from sitting: standing up until a calm spell completes
            quiet = np.flatnonzero(calm_run[i:j])
            end_up = i + (quiet[0] if quiet.size else j - i)
            labels[i:end_up] = 'standing_up'
        else:
            end_up = i
        if j < n:  # goes back to sitting: sitting down after the last calm spell
            quiet = np.flatnonzero(calm_run[end_up:j])
            start_down = end_up + quiet[-1] + 1 if quiet.size else end_up
            labels[start_down:j] = 'sitting_down'
        else:
            start_down = j
        mid = stretch[(stretch >= end_up) & (stretch < start_down)]
        labels[mid[moving[mid]]] = 'moving_joints'
        i = j
    return labels
