"""krang metrics: the paper's Table II figures for one balancing run, plus physical versions."""

import argparse
import json
import math

DESCRIPTION = """\
Compute the five Table II figures of one balancing log (a kit CSV from
krang_data/balancing_runs/, or one of our MCAP bags), in two definitions.

Paper definitions (exactly as the authors' analysis, quirks kept; the data kit's README.md,
../shared/krang_data or $KRANG_DATA):
  motion start = first sample where the 20-sample centred moving average of the LEFT commanded
  current exceeds 1 A in magnitude; the window is the next 55 s.
  max_position_m        0.27 x the largest smoothed left current (a current in A times 0.27,
                        although the paper labels it a position in m)
  resting_position_m    |0.27 x mean of x_wheel (rad) from 20 s to 55 s|
  time_until_resting_s  last time x is more than 0.3 rad from that resting value (read on the
                        log's own clock at the sample count from motion start, as the authors did)
  max_power_w           max over the first 10 s of |tau w|, tau = smoothed left current x 15 x
                        12 x 0.00706 N m, w = ground-referenced wheel speed (one wheel)
  avg_resting_power_mw  1000 x mean over 10-55 s of |tau w| x dt: mJ per control step, not mW

Physical definitions (under "physical"; the robot's drive train, krang_model.drivetrain: gear
ratio and torque constant from config/robot.yaml, wheel radius from the URDF or --wheel-radius):
  max_displacement_m, resting_displacement_m (signed, from the motion-start position),
  settle_time_s (band --settle-band in m), peak/mean mechanical and electrical power of BOTH
  wheels from the raw commanded currents and the wheel speeds relative to the body, in W
  (mean = energy / time over 10-55 s), and the paper's integrand averaged as a true power.
"""


def register(subparsers):
    p = subparsers.add_parser(
        'metrics',
        help="Table II metrics of one balancing run (paper's and physical definitions)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument('run', metavar='RUN', help='balancing log: kit CSV or our MCAP bag')
    p.add_argument(
        '--json',
        action='store_true',
        help='print the result as one JSON object on the last stdout line: '
        '{"max_position_m", "resting_position_m", "time_until_resting_s", '
        '"max_power_w", "avg_resting_power_mw", "physical": {...}}',
    )
    p.add_argument(
        '--wheel-radius',
        type=float,
        default=None,
        metavar='M',
        help='wheel radius in m for the physical metrics (default: the URDF wheel)',
    )
    p.add_argument(
        '--settle-band',
        type=float,
        default=0.08,
        metavar='M',
        help='physical settle band around the resting point, m (default 0.08)',
    )
    p.set_defaults(func=run)


def _fmt(v, unit=''):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return 'n/a'
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return f'{v:.4g}{unit}'
    return f'{v}{unit}'


def load_bag_run(path):
    """One of our MCAP bags as a balancing run (the discrepancy workflow's bag loader)."""
    from krang_adrc_controller.metrics import run_from_record
    from krang_discrepancy.loaders import load_bag_record

    return run_from_record(load_bag_record(path))


def run(args):
    from krang_adrc_controller.metrics import (
        PAPER_KEYS,
        compute_metrics,
        load_run,
        register_loader,
    )

    register_loader('.mcap', load_bag_run)
    log = load_run(args.run)
    result = compute_metrics(log, args.wheel_radius, settle_band_m=args.settle_band)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f'run: {log.source or log.name} ({len(log)} samples, {log.t[-1]:.1f} s)')
    print("paper's definitions (Table II, quirks kept):")
    for k in PAPER_KEYS:
        print(f'  {k:28s} {_fmt(result[k])}')
    print('physical definitions:')
    for k, v in result['physical'].items():
        print(f'  {k:38s} {_fmt(v)}')
    if not result['physical'].get('complete_window', True):
        print('warning: the run ends before the 55 s window does; figures cover what was logged')
    return 0
