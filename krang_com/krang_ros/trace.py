"""Where a sample's latency goes: wall-clock times of each IMU sample at each stage of the control
path, written only when the environment variable KRANG_TRACE names a file prefix.

bench/bench_ros_latency.py --robot --trace sets it for can_bridge and adrc_controller. Each
process then appends one line per sample and stage to `<prefix>.<pid>`: the stage, the sample's
/imu/data header stamp (the key that follows the sample across processes: the wheel command
carries it back) and the stage's times from time.time(), the clock of the kernel's CAN frame
stamps. Stages (STAGES): `imu_in` (can_bridge: the DMU frame that completed the sample in the
kernel, its handling started, /imu/data published), `step` (adrc_controller: the callback started,
the wheel command published), `cmd_out` (can_bridge: the command's callback started, the current
frames sent). Off, a stage costs the test of `ON`; on, about 3 us (2.5 us a line measured here),
and the files grow by about 0.4 GB an hour at 500 Hz (some 210 bytes a sample): a tool for
measurement runs, not for a robot's day.
"""

from __future__ import annotations

import atexit
import os
import threading
import time
from typing import Iterable, Mapping

ENV = 'KRANG_TRACE'
STAGES = {'imu_in': 3, 'step': 2, 'cmd_out': 2}  # stage -> number of times after the stamp
_prefix = os.environ.get(ENV, '')
ON = bool(_prefix)
now = time.time
_file = None
_lock = threading.Lock()  # the bridge records from its receive thread and its executor's


def record(stage: str, stamp, *times: float) -> None:
    """One line: `stage`, the sample's stamp (a builtin_interfaces Time) and `times`."""
    global _file
    line = f'{stage} {stamp.sec + stamp.nanosec * 1e-9!r} {" ".join(map(repr, times))}\n'
    with _lock:
        if _file is None:
            _file = open(f'{_prefix}.{os.getpid()}', 'ab')  # noqa: SIM115
            atexit.register(_file.close)
        _file.write(line.encode())


def read(paths: Iterable[str]) -> dict[str, dict[float, tuple[float, ...]]]:
    """stage -> {stamp: times} from the files of every process; a stamp's first line of a stage
    wins (a second command answering the same sample is not its answer). A line cut short (a
    process killed while writing it) is skipped."""
    out: dict[str, dict[float, tuple[float, ...]]] = {s: {} for s in STAGES}
    for path in paths:
        with open(path, errors='replace') as f:
            for line in f:
                if not line.endswith('\n'):
                    continue
                fields = line.split()
                stage = fields[0] if fields else ''
                if stage in STAGES and len(fields) == 2 + STAGES[stage]:
                    try:
                        values = tuple(map(float, fields[1:]))
                    except ValueError:
                        continue
                    out[stage].setdefault(values[0], values[1:])
    return out


# (segment, its start and end: (stage, index into that stage's times))
SEGMENTS = (
    ('bridge receives the frame', ('imu_in', 0), ('imu_in', 1)),
    ('bridge decodes, filters, publishes', ('imu_in', 1), ('imu_in', 2)),
    ('DDS to adrc_controller', ('imu_in', 2), ('step', 0)),
    ('adrc_controller steps, publishes', ('step', 0), ('step', 1)),
    ('DDS to can_bridge', ('step', 1), ('cmd_out', 0)),
    ('bridge encodes, sends', ('cmd_out', 0), ('cmd_out', 1)),
)


def segments(
    traced: Mapping[str, Mapping[float, tuple[float, ...]]], since: float, until: float
) -> dict[str, list[float]]:
    """Each segment's durations [s] over the samples traced through every stage whose frame came
    between `since` and `until`, and `total` (frame in the kernel to current frames sent): the
    segments of one sample add up to its total."""
    keys = [
        k
        for k in sorted(set.intersection(*(set(traced[s]) for s in STAGES)))
        if since <= traced['imu_in'][k][0] <= until
    ]
    out = {
        name: [traced[b[0]][k][b[1]] - traced[a[0]][k][a[1]] for k in keys]
        for name, a, b in SEGMENTS
    }
    out['total'] = [traced['cmd_out'][k][1] - traced['imu_in'][k][0] for k in keys]
    return out
