"""Table II metrics of one balancing run: the authors' definitions (quirks kept) and physical ones.

Layers, so other log sources plug in:
  * ``BalancingRun``: a small time-series container (t, dt, currents, wheel x and speed, ...).
  * loaders: ``load_hardware_csv`` reads the kit's CSV logs (time = cumsum(dt_s)); ``load_run``
    dispatches on the file suffix through ``LOADERS``. A bag (MCAP) loader is added elsewhere with
    ``register_loader('.mcap', fn)``; ``fn(path) -> BalancingRun`` must follow the container's
    conventions (below).
  * math: ``paper_metrics(run)`` and ``physical_metrics(run, drive)`` (a ``Drivetrain``);
    ``compute_metrics`` bundles both into the JSON shape of ``krang metrics --json``.

Container conventions: t in s from the start of the log (the CSV gives t = cumsum(dt), so t[0] =
dt[0]); dt[k] = duration of the loop that ended at sample k; currents = commanded motor currents
in A, positive = torque that drives x forward (checked on the kit runs: current correlates
positively with wheel speed and acceleration); x_wheel_rad / dx_wheel_rad_s = ground-referenced
wheel angle and speed (encoders + IMU pitch); dtheta_rad_s = IMU pitch rate; dpsi = (right -
left) / 2 wheel speed.

The authors' definitions (the data kit's README.md, "The Table II metrics"; the kit is
../shared/krang_data or $KRANG_DATA), reproduced exactly:
  * s = 20-sample centred moving average of the left current, s[k] = mean(i[k-9 .. k+10])
    (zero-padded at the ends, np.convolve style). This alignment reproduces the kit's table; the
    other centring, mean(i[k-10 .. k+9]), moves Max Power by ~1.4 W (beta16) and misses it.
  * motion start = first sample with |s| > 1 A; the window is the samples with t - t_start <= 55 s.
  * Max Pos = 0.27 x max(s) over the window: a *current* (A) times 0.27, though labelled metres.
  * Resting Pos = |0.27 x mean(x) over 20..55 s| (the paper prints the magnitude).
  * Time until Resting: k = window index of the last sample with |x - mean_rest| > 0.3 rad; the
    value is the log's un-shifted clock at window index k + 1, t[k + 1], i.e. the time axis from
    the start of the log read at the sample count from motion start. This reproduces the kit's
    numbers (t[k] is ~0.03 s short on every beta).
  * Max Power = max over the first 10 s of |tau w|, tau = s x 15 x 12 x 0.00706 N m, w = dx_wheel:
    one wheel, ground-referenced speed.
  * Avg Resting Power = 1000 x mean over 10..55 s of |tau w| x dt: energy per control step in mJ,
    not a power.
The physical versions are documented in ``physical_metrics``.
"""

from __future__ import annotations

import csv
import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from krang_model.drivetrain import Drivetrain, drivetrain
from krang_model.robot import load_krang

# ----------------------------------------------------------------------------- container


@dataclass
class BalancingRun:
    """Time series of one balancing run (see the module docstring for conventions)."""

    t: np.ndarray
    i_left: np.ndarray
    i_right: np.ndarray
    x_wheel_rad: np.ndarray
    dx_wheel_rad_s: np.ndarray
    dt: np.ndarray | None = None
    theta_rad: np.ndarray | None = None
    dtheta_rad_s: np.ndarray | None = None
    psi_wheel_rad: np.ndarray | None = None
    dpsi_wheel_rad_s: np.ndarray | None = None
    q_base_rad: np.ndarray | None = None
    name: str = ''
    source: str = ''
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        self.t = np.asarray(self.t, float).ravel()
        n = self.t.size
        if n < 2:
            raise ValueError('a run needs at least two samples')
        if np.any(np.diff(self.t) < 0):
            raise ValueError('time must be non-decreasing')
        for name in (
            'i_left',
            'i_right',
            'x_wheel_rad',
            'dx_wheel_rad_s',
            'dt',
            'theta_rad',
            'dtheta_rad_s',
            'psi_wheel_rad',
            'dpsi_wheel_rad_s',
            'q_base_rad',
        ):
            v = getattr(self, name)
            if v is None:
                continue
            v = np.asarray(v, float).ravel()
            if v.size != n:
                raise ValueError(f'{name} has {v.size} samples, t has {n}')
            setattr(self, name, v)
        if self.dt is None:
            # duration of the loop ending at each sample; the first one is t[0] if the clock
            # starts at 0 with the log, else one median period
            first = self.t[0] if self.t[0] > 0 else float(np.median(np.diff(self.t)))
            self.dt = np.concatenate([[first], np.diff(self.t)])

    def __len__(self):
        return self.t.size


# ----------------------------------------------------------------------------- loaders

HARDWARE_CSV_COLUMNS = {
    'dt_s': 'dt',
    'i_cmd_left_A': 'i_left',
    'i_cmd_right_A': 'i_right',
    'theta_com_rad': 'theta_rad',
    'dtheta_com_rad_s': 'dtheta_rad_s',
    'x_wheel_rad': 'x_wheel_rad',
    'dx_wheel_rad_s': 'dx_wheel_rad_s',
    'psi_wheel_rad': 'psi_wheel_rad',
    'dpsi_wheel_rad_s': 'dpsi_wheel_rad_s',
    'q_base_rad': 'q_base_rad',
}


def read_log_columns(path, need, optional=(), min_rows=2) -> dict:
    """{column: values} of a kit balancing log (CSV with a header), checked: every `need` column
    present, at least `min_rows` rows, every value of the columns read finite. Each problem is a
    ValueError naming the file (one line on the command line). `krang metrics` and the
    discrepancy workflow both read the kit's logs through this."""
    path = Path(path)
    with open(path, newline='') as f:
        header = next(csv.reader(f), None)
    if not header:
        raise ValueError(f'{path}: empty file, not a balancing log')
    missing = [c for c in need if c not in header]
    if missing:
        raise ValueError(f'{path}: not a balancing log, missing columns {missing}')
    try:
        with warnings.catch_warnings():  # a header-only file is reported below, in one line
            warnings.simplefilter('ignore', UserWarning)
            data = np.loadtxt(path, delimiter=',', skiprows=1, ndmin=2)
    except ValueError as err:
        raise ValueError(f'{path}: unreadable row ({err})') from None
    if data.shape[0] < min_rows or data.shape[1] != len(header):
        raise ValueError(
            f'{path}: {data.shape[0]} data rows of {len(header)} columns; a run needs at least '
            f'{min_rows}'
        )
    cols = {c: data[:, header.index(c)] for c in (*need, *optional) if c in header}
    for c, values in cols.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise ValueError(
                f'{path}: {c} is NaN or infinite in {bad.size} rows (first: data row {bad[0] + 1})'
            )
    return cols


def load_hardware_csv(path) -> BalancingRun:
    """A kit balancing log (balancing_runs/*/*.csv, 33-beta-testing state dump + header)."""
    need = [c for c in HARDWARE_CSV_COLUMNS if c != 'q_base_rad']
    cols = read_log_columns(path, need, optional=('q_base_rad',))
    run = {HARDWARE_CSV_COLUMNS[c]: v for c, v in cols.items()}
    return BalancingRun(t=np.cumsum(run['dt']), name=Path(path).stem, source=str(path), **run)


def run_from_record(rec, drive: Drivetrain | None = None) -> BalancingRun:
    """A BalancingRun from a measured record (krang_discrepancy.record.Record: a bag of ours).

    The commanded currents are the recorded wheel-torque commands, held until the next one and
    divided by Kt x gear; x_wheel is the ground-referenced wheel angle (encoders + IMU pitch), as
    in the hardware logs."""
    drive = drive or drivetrain(load_krang())
    held = np.searchsorted(rec.cmd_t, rec.t, side='right') - 1
    torque = np.where(held[:, None] >= 0, rec.cmd_torque[np.maximum(held, 0)], 0.0)
    current = torque / (drive.torque_constant * drive.gear_ratio)
    return BalancingRun(
        t=rec.t,
        i_left=current[:, 0],
        i_right=current[:, 1],
        x_wheel_rad=rec.wheel + rec.q_base,
        dx_wheel_rad_s=rec.wheel_rate + rec.pitch_rate,
        q_base_rad=rec.q_base,
        name=rec.name,
        source=rec.source,
    )


#: suffix -> loader(path) -> BalancingRun. Add bag readers with ``register_loader``.
LOADERS: dict[str, Callable[[Path], BalancingRun]] = {'.csv': load_hardware_csv}


def register_loader(suffix: str, loader: Callable[[Path], BalancingRun]) -> None:
    """Hook for other log formats, e.g. register_loader('.mcap',
    krang_bag.reader.balancing_run)."""
    LOADERS[suffix.lower() if suffix.startswith('.') else '.' + suffix.lower()] = loader


def load_run(path) -> BalancingRun:
    path = Path(path)
    loader = LOADERS.get(path.suffix.lower())
    if loader is None:
        raise ValueError(f'no loader for {path.suffix!r} files (known: {sorted(LOADERS)})')
    return loader(path)


# ----------------------------------------------------------------------------- paper math


@dataclass(frozen=True)
class PaperDefinition:
    """The authors' analysis constants (part of the metric's definition, not robot config)."""

    smoothing_window: int = 20
    motion_threshold_a: float = 1.0
    window_s: float = 55.0
    position_scale: float = 0.27  # the authors' wheel radius
    resting_from_s: float = 20.0
    resting_band_rad: float = 0.3
    peak_power_window_s: float = 10.0
    resting_power_from_s: float = 10.0
    gear_ratio: float = 15.0
    torque_constant_nm_per_a: float = 12 * 0.00706


PAPER = PaperDefinition()


def centred_moving_average(x, n: int) -> np.ndarray:
    """s[k] = sum(x[k - n//2 + 1 .. k + n//2]) / n for even n (x zero-padded), the alignment of the
    authors' analysis; for odd n the symmetric window."""
    x = np.asarray(x, float)
    full = np.convolve(x, np.ones(n) / n, mode='full')
    return full[n // 2 : n // 2 + x.size]


@dataclass
class _Window:
    start: int
    end: int  # exclusive
    smoothed: np.ndarray  # whole run
    rel: np.ndarray  # t - t[start], whole run
    complete: bool  # the run lasts the full window after motion start


def _window(run: BalancingRun, d: PaperDefinition) -> _Window:
    s = centred_moving_average(run.i_left, d.smoothing_window)
    above = np.flatnonzero(np.abs(s) > d.motion_threshold_a)
    if above.size == 0:
        raise ValueError(
            f'{run.name or "run"}: no motion (smoothed left current never exceeds '
            f'{d.motion_threshold_a} A)'
        )
    st = int(above[0])
    rel = run.t - run.t[st]
    end = st + int(np.count_nonzero(rel[st:] <= d.window_s))
    complete = bool(rel[-1] >= d.window_s)
    return _Window(st, end, s, rel, complete)


def _nan_to_none(v):
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else v


def paper_metrics(run: BalancingRun, definition: PaperDefinition = PAPER) -> dict:
    """The five Table II figures for one run, computed as the authors did (module docstring)."""
    d = definition
    w = _window(run, d)
    sl = slice(w.start, w.end)
    s, x, rel = w.smoothed[sl], run.x_wheel_rad[sl], w.rel[sl]
    dx, dt = run.dx_wheel_rad_s[sl], run.dt[sl]
    rest_mask = (rel >= d.resting_from_s) & (rel <= d.window_s)
    rest = float(np.mean(x[rest_mask])) if rest_mask.any() else math.nan
    if math.isnan(rest):
        t_rest = math.nan
    else:
        out = np.flatnonzero(np.abs(x - rest) > d.resting_band_rad)
        if out.size == 0:
            t_rest = 0.0
        else:
            k = min(int(out[-1]) + 1, run.t.size - 1)
            t_rest = float(run.t[k])
    power = np.abs(s * d.gear_ratio * d.torque_constant_nm_per_a * dx)
    early = rel <= d.peak_power_window_s
    late = (rel >= d.resting_power_from_s) & (rel <= d.window_s)
    return {
        'max_position_m': float(d.position_scale * np.max(s)),
        'resting_position_m': abs(d.position_scale * rest),
        'time_until_resting_s': t_rest,
        'max_power_w': float(np.max(power[early])),
        'avg_resting_power_mw': float(np.mean(power[late] * dt[late]) * 1000.0)
        if late.any()
        else math.nan,
        'motion_start_index': w.start,
        'motion_start_s': float(run.t[w.start]),
        'complete_window': w.complete,
    }


# ----------------------------------------------------------------------------- physical math

#: Winding resistance of the BLY343D line to line, ohm (krang_model/README.md); not part of the
#: drive-train description, which the controller and the simulator share.
DEFAULT_WINDING_RESISTANCE_OHM = 0.09


def physical_metrics(
    run: BalancingRun,
    drive: Drivetrain,
    *,
    winding_resistance_ohm: float = DEFAULT_WINDING_RESISTANCE_OHM,
    settle_band_m: float = 0.08,
    definition: PaperDefinition = PAPER,
) -> dict:
    """What the Table II columns mean physically, on the same motion start and 55 s window, with
    the wheel radius, gear ratio and torque constant of ``drive``.

    * max_displacement_m = r max|x - x_start|, x_start = x at motion start.
    * resting_displacement_m = r (mean x over 20..55 s - x_start), signed (negative = behind).
    * settle_time_s: time since motion start (shifted clock) of the first sample after the last
      one farther than settle_band_m (default 0.08 m, ~ the paper's 0.3 rad) from the rest point.
    * Powers use the *raw* commanded currents of both wheels, tau_w = gear Kt i_w at the wheel, and
      each wheel's speed relative to the body (the motor's shaft speed / gear): dx - dtheta -/+
      dpsi (left/right). Without dtheta in the log the ground-referenced dx is used (flagged).
      mech = sum_w |tau_w w_w|; electrical (net, both motors) = sum_w (R i_w^2 + tau_w w_w).
    * peak_* over the whole window; mean_resting_* = energy / time over 10..55 s (the paper's
      "resting" interval), in W.
    * mean_resting_power_paper_integrand_w: the paper's own integrand (one wheel, smoothed current,
      ground speed) averaged properly (energy / time) instead of mJ per step.
    """
    if drive.wheel_radius <= 0:
        raise ValueError('the wheel radius must be positive')
    d = definition
    w = _window(run, d)
    sl = slice(w.start, w.end)
    x, rel, dt = run.x_wheel_rad[sl], w.rel[sl], run.dt[sl]
    r = float(drive.wheel_radius)
    x0 = float(x[0])
    rest_mask = (rel >= d.resting_from_s) & (rel <= d.window_s)
    rest = float(np.mean(x[rest_mask])) if rest_mask.any() else math.nan
    if math.isnan(rest):
        settle = math.nan
    else:
        out = np.flatnonzero(r * np.abs(x - rest) > settle_band_m)
        settle = 0.0 if out.size == 0 else float(rel[min(int(out[-1]) + 1, x.size - 1)])

    relative_speed = run.dtheta_rad_s is not None
    w_mean = run.dx_wheel_rad_s[sl] - (run.dtheta_rad_s[sl] if relative_speed else 0.0)
    w_spin = run.dpsi_wheel_rad_s[sl] if run.dpsi_wheel_rad_s is not None else 0.0
    i_l, i_r = run.i_left[sl], run.i_right[sl]
    k = drive.gear_ratio * drive.torque_constant
    p_l = k * i_l * (w_mean - w_spin)
    p_r = k * i_r * (w_mean + w_spin)
    mech = np.abs(p_l) + np.abs(p_r)
    elec = winding_resistance_ohm * (i_l**2 + i_r**2) + p_l + p_r
    paper_integrand = np.abs(
        w.smoothed[sl] * d.gear_ratio * d.torque_constant_nm_per_a * run.dx_wheel_rad_s[sl]
    )
    late = (rel >= d.resting_power_from_s) & (rel <= d.window_s)

    def mean_power(p):
        return float(np.sum(p[late] * dt[late]) / np.sum(dt[late])) if late.any() else math.nan

    return {
        'wheel_radius_m': r,
        'max_displacement_m': float(r * np.max(np.abs(x - x0))),
        'resting_displacement_m': r * (rest - x0),
        'settle_time_s': settle,
        'settle_band_m': float(settle_band_m),
        'peak_mechanical_power_w': float(np.max(mech)),
        'peak_electrical_power_w': float(np.max(elec)),
        'mean_resting_mechanical_power_w': mean_power(mech),
        'mean_resting_electrical_power_w': mean_power(elec),
        'mean_resting_power_paper_integrand_w': mean_power(paper_integrand),
        'wheel_speed_relative_to_body': relative_speed,
        'window_s': float(min(d.window_s, rel[-1])),
        'motion_start_s': float(run.t[w.start]),
    }


# ----------------------------------------------------------------------------- bundle


PAPER_KEYS = (
    'max_position_m',
    'resting_position_m',
    'time_until_resting_s',
    'max_power_w',
    'avg_resting_power_mw',
)


def compute_metrics(
    run: BalancingRun,
    wheel_radius_m: float | None = None,
    *,
    drive: Drivetrain | None = None,
    settle_band_m: float = 0.08,
    definition: PaperDefinition = PAPER,
) -> dict:
    """Both definitions in the ``krang metrics --json`` shape (NaN -> None). The physical ones use
    ``drive`` (default: the robot's, krang_model.drivetrain), its wheel radius replaced by
    ``wheel_radius_m`` when given."""
    paper = paper_metrics(run, definition)
    if drive is None:
        drive = drivetrain(load_krang())
    source = 'krang_model URDF wheel cylinder'
    if wheel_radius_m is not None:
        drive, source = replace(drive, wheel_radius=float(wheel_radius_m)), 'argument'
    phys = physical_metrics(run, drive, settle_band_m=settle_band_m, definition=definition)
    phys['wheel_radius_source'] = source
    phys['torque_constant_nm_per_a'] = drive.torque_constant
    phys['gear_ratio'] = drive.gear_ratio
    phys['complete_window'] = paper['complete_window']
    out = {k: _nan_to_none(paper[k]) for k in PAPER_KEYS}
    out['physical'] = {k: _nan_to_none(v) for k, v in phys.items()}
    return out
