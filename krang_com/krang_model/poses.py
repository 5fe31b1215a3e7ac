"""Pose CSV files: q_base plus the body joints in pose order (columns of the hardware CSV)."""

import csv
import math
from pathlib import Path

import numpy as np

from .files import atomic_open


class PoseFileError(ValueError):
    """A pose file that cannot be read."""


def load_poses(path, robot_columns, limits=None):
    """(q_base (N,), joints (N, J), rows as dicts) from a pose CSV; extra columns are ignored.

    q_base is the base's pitch, an angle: a value outside [-pi, pi] is a corrupt file.

    `limits` = (lower, upper) of the joints: a pose outside them is an error, not a silent
    extrapolation of the model to a configuration the robot cannot take."""
    path = Path(path)
    if not path.exists():
        raise PoseFileError(f'{path}: no such pose file')
    with open(path, newline='') as f:
        reader = csv.DictReader(f)
        header = reader.fieldnames or []
        needed = ['q_base', *robot_columns]
        missing = [c for c in needed if c not in header]
        if missing:
            raise PoseFileError(f'{path}: missing columns {missing}')
        rows = list(reader)
    short = [i + 2 for i, r in enumerate(rows) if any(r.get(c) in (None, '') for c in needed)]
    if short:
        raise PoseFileError(
            f'{path}: line {short[0]} has fewer values than the header (truncated file?)'
        )
    try:
        table = np.array([[float(r[c]) for c in needed] for r in rows], dtype=float).reshape(
            -1, len(needed)
        )
    except ValueError as err:
        raise PoseFileError(f'{path}: non-numeric value ({err})') from None
    bad = ~np.all(np.isfinite(table), axis=1)
    if bad.any():
        raise PoseFileError(f'{path}: NaN/inf in rows {np.flatnonzero(bad)[:10].tolist()}')
    pitch_out = np.abs(table[:, 0]) > math.pi
    if pitch_out.any():
        i = int(np.flatnonzero(pitch_out)[0])
        raise PoseFileError(
            f'{path}: line {i + 2}: q_base = {table[i, 0]:.6g} rad is not a pitch (outside '
            f'[-pi, pi]; {int(pitch_out.sum())} rows)'
        )
    if limits is not None:
        _check_limits(path, table[:, 1:], needed[1:], *limits)
    return table[:, 0], table[:, 1:], rows


def _check_limits(path, joints, columns, lower, upper, tol=1e-9):
    outside = (joints < np.asarray(lower) - tol) | (joints > np.asarray(upper) + tol)
    if outside.any():
        i, j = np.argwhere(outside)[0]
        raise PoseFileError(
            f'{path}: line {i + 2}: {columns[j]} = {joints[i, j]:.6g} rad is outside '
            f'the joint limits [{lower[j]:.6g}, {upper[j]:.6g}] '
            f'({int(outside.any(axis=1).sum())} poses outside)'
        )


def save_poses(path, q_base, joints, robot_columns, extra=None):
    """Write a pose CSV; `extra` maps column name -> per-row values."""
    path = Path(path)
    extra = extra or {}
    with atomic_open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(['q_base', *robot_columns, *extra])
        for i, (qb, q) in enumerate(zip(q_base, joints)):
            w.writerow([f'{qb:.9g}', *(f'{v:.9g}' for v in q), *(extra[k][i] for k in extra)])
    return path
