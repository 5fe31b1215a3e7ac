"""Pose CSV files: q_base plus the body joints in pose order (columns of the hardware CSV)."""
import csv
from pathlib import Path

import numpy as np


class PoseFileError(ValueError):
    """A pose file that cannot be read."""


def load_poses(path, robot_columns):
    """(q_base (N,), joints (N, J), rows as dicts) from a pose CSV; extra columns are ignored."""
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
    try:
        table = np.array([[float(r[c]) for c in needed] for r in rows], dtype=float).reshape(-1, len(needed))
    except ValueError as err:
        raise PoseFileError(f'{path}: non-numeric value ({err})') from None
    bad = ~np.all(np.isfinite(table), axis=1)
    if bad.any():
        raise PoseFileError(f'{path}: NaN/inf in rows {np.flatnonzero(bad)[:10].tolist()}')
    return table[:, 0], table[:, 1:], rows


def save_poses(path, q_base, joints, robot_columns, extra=None):
    """Write a pose CSV; `extra` maps column name -> per-row values."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = extra or {}
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(['q_base', *robot_columns, *extra])
        for i, (qb, q) in enumerate(zip(q_base, joints)):
            w.writerow([f'{qb:.9g}', *(f'{v:.9g}' for v in q), *(extra[k][i] for k in extra)])
    return path
