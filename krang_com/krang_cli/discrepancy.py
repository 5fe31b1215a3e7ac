"""krang discrepancy: find where simulation and measured data disagree, name the missing effect,
add it to the model and show the gap shrink."""

import argparse

DESCRIPTION = """\
Compare the nominal Krang model with measured data, name the physical effect the model is missing,
add it, and show the gap before and after.

DATA is one or more kit CSV logs (krang_data/balancing_runs/*/*.csv: ~30 Hz, commanded currents),
MCAP bags from `krang demo` / `mcap_recorder` (/joint_states, /imu/data, /wheel_effort_cmd), or
folders of them. All records are put on one uniform clock.

Steps:
  1. replay   the nominal model predicts the measured pitch, pitch rate, wheel angle and wheel rate
              HORIZON seconds ahead from every measured state (multiple shooting; the balancing
              robot is unstable, so one long open-loop rollout would only measure its divergence),
              driven by the measured commands and body pose;
  2. locate   where the predictions fail: per phase (sitting, standing_up, balancing,
              moving_joints, sitting_down) and signal, with bias, RMS, autocorrelation and the
              worst stretches;
  3. name     fit every effect of the library (and pairs), keep the one that improves predictions
              of HELD-OUT data (interleaved time blocks) by at least --min-improvement with a
              paired t over blocks >= --min-t; report "none" when nothing qualifies;
  4. check    is what is left structured? Generic forces (torque, its sign, speeds, pitch, time)
              fitted to the residual on held-out blocks: if they still predict it, or (with
              --baseline) the model stays more than 2x its own typical error off, the answer is
              "unexplained" with the residual's signature, never a wrong name or "none";
  5. extend   write DIR/extended_model.yaml (the effects of krang_model.effects and their
              values: what `krang experiment table2 --extended-model` simulates), re-simulate
              every window with it, report the gap.

With --baseline EXTENDED_MODEL.yaml the new data are judged against the robot as earlier runs
corrected it: the gap is in units of that model's typical error on its own data, the effects named
are what changed (values physical: a torque constant in N m/A), and the extended model written is
complete (baseline + new effects), so it can be the next baseline.

Effects in the library: imu_pitch_bias (rad), floor_slope (rad), wheel_radius (m), payload (kg on
lGripper / rGripper), wheel_viscous_friction (N m s), wheel_coulomb_friction (N m per wheel),
torque_constant (N m/A), actuation_delay (s), encoder_offset (rad, JWaist). Add your own with
--effects-module (see krang_model/effects.py).

Outputs: DIR/report.md with figures (locate_*.png, naming_evidence.png, gap_*.png),
DIR/extended_model.yaml, DIR/result.json. The gap is the RMS prediction error of the four signals
over the fitting phases, each signal in units of the nominal model's typical (robust RMS) error for
it: about 1 before, the share left after; gap_pitch_rad and gap_wheel_rad give the pitch and
wheel-angle errors at the horizon in rad, [before, after].
"""


def register(subparsers):
    p = subparsers.add_parser(
        'discrepancy',
        help='find where sim and measured data disagree, name the missing effect, show the gap '
        'shrink',
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        '--measured',
        nargs='+',
        required=True,
        metavar='DATA',
        help='measured data: kit CSV logs, MCAP bags, or folders of them',
    )
    p.add_argument(
        '--out',
        required=True,
        metavar='DIR',
        help='output folder (report.md, PNGs, extended_model.yaml)',
    )
    p.add_argument(
        '--json',
        action='store_true',
        help='print {"effect", "value", "unit", "uncertainty", "gap_before", "gap_after"} (or '
        '{"effects": [...], ...} for a combination; effect "none" when nothing is found) '
        'as the last stdout line',
    )
    p.add_argument(
        '--baseline',
        metavar='YAML',
        default=None,
        help='an extended_model.yaml of earlier runs: judge the new data against it',
    )
    p.add_argument(
        '--beta',
        metavar='FILE',
        default=None,
        help='mass model of the nominal robot (default: config/sim_true_beta.yaml, the fit to '
        'the real balanced poses)',
    )
    p.add_argument(
        '--effects',
        metavar='LIST',
        default=None,
        help='comma-separated effect names or keys to consider (default: the whole library)',
    )
    p.add_argument(
        '--extra-effects',
        action='store_true',
        help='also consider the optional effects body_inertia (kg m^2), drive_current_limit (A) '
        'and com_height (m), which the simulator cannot produce',
    )
    p.add_argument(
        '--effects-module',
        metavar='MODULE',
        action='append',
        default=[],
        help='import a module or .py file that registers extra effects (repeatable)',
    )
    p.add_argument(
        '--horizon',
        type=float,
        default=0.3,
        metavar='S',
        help='prediction horizon, s (default 0.3)',
    )
    p.add_argument(
        '--stride',
        type=float,
        default=0.05,
        metavar='S',
        help='a window every S seconds (default 0.05)',
    )
    p.add_argument(
        '--max-windows',
        type=int,
        default=None,
        metavar='N',
        help='at most N windows over all records: beyond, the stride widens alike for all '
        '(default 20000: 30 min of 30 Hz logs at a stride of 0.1 s, about 45 s on two cores; '
        '0: no limit)',
    )
    p.add_argument(
        '--pose-delay',
        type=float,
        default=0.0,
        metavar='S',
        help='the body pose follows the measured joints S seconds later (joint-state latency; '
        'the simulated plant updates a moving pose every 20 ms, i.e. 0.01 s on average; '
        'default 0)',
    )
    p.add_argument(
        '--rate',
        type=float,
        default=None,
        metavar='HZ',
        help="resample the measurements to this rate (default: the data's own)",
    )
    p.add_argument(
        '--phases',
        default=None,
        metavar='LIST',
        help='phases used for naming (default: all, sitting,standing_up,balancing,moving_joints,'
        'sitting_down)',
    )
    p.add_argument(
        '--min-improvement',
        type=float,
        default=None,
        metavar='F',
        help='minimum share of the held-out loss an effect must remove (default 0.10)',
    )
    p.add_argument(
        '--min-t',
        type=float,
        default=None,
        metavar='T',
        help='minimum paired t over blocks (default 3)',
    )
    p.add_argument(
        '--max-effects',
        type=int,
        default=None,
        metavar='N',
        help='largest combination (default 3)',
    )
    p.add_argument(
        '--folds', type=int, default=None, metavar='K', help='cross-validation folds (default 2)'
    )
    p.add_argument(
        '--block',
        type=float,
        default=None,
        metavar='S',
        help='cross-validation block length, s (default 2)',
    )
    p.add_argument(
        '--workers',
        type=int,
        default=0,
        metavar='N',
        help='threads of the prediction (default 0: the cores, at most 4)',
    )
    p.add_argument('--no-plots', action='store_true', help='skip the figures')
    p.set_defaults(func=run)


def run(args):
    import sys

    from krang_discrepancy.nominal import NominalModel
    from krang_discrepancy.phases import PHASES
    from krang_discrepancy.replay import ReplayConfig
    from krang_model.effects import load_effects_module, register_optional_effects
    from krang_discrepancy.naming import NamingConfig
    from krang_discrepancy.report import run_discrepancy
    from krang_cli.common import print_json

    if args.extra_effects:
        register_optional_effects()
    for mod in args.effects_module:
        load_effects_module(mod)
    ncfg = NamingConfig()
    for name, attr in (
        ('min_improvement', 'min_improvement'),
        ('min_t', 'min_t'),
        ('max_effects', 'max_effects'),
        ('folds', 'folds'),
        ('block', 'block_s'),
    ):
        v = getattr(args, name)
        if v is not None:
            setattr(ncfg, attr, v)
    rcfg = ReplayConfig(
        horizon_s=args.horizon,
        stride_s=args.stride,
        max_total_windows=(
            ReplayConfig.max_total_windows if args.max_windows is None else args.max_windows
        ),
        pose_delay_s=args.pose_delay,
        workers=args.workers,
    )
    phases = tuple(s.strip() for s in args.phases.split(',')) if args.phases else None
    if phases and not set(phases) <= set(PHASES):
        raise ValueError(
            f'unknown phases {sorted(set(phases) - set(PHASES))}; known: {", ".join(PHASES)}'
        )
    cands = [s.strip() for s in args.effects.split(',')] if args.effects else None
    model = NominalModel.default(args.beta) if args.beta or not args.baseline else None

    def say(msg):
        print(msg, file=sys.stderr if args.json else sys.stdout)

    out = run_discrepancy(
        args.measured,
        args.out,
        model=model,
        candidates=cands,
        replay_config=rcfg,
        naming_config=ncfg,
        phases=phases,
        plots=not args.no_plots,
        rate_hz=args.rate,
        log=say,
        baseline=args.baseline,
    )
    js = out['json']
    if args.json:
        print_json(js)
    else:
        if js.get('effect') == 'unexplained':
            print(f'unexplained: {js["reason"]}')
            print(
                f'gap {js["gap_before"]:.4g} -> {js["gap_after"]:.4g} with the partial library '
                'correction'
            )
        elif js.get('effect') == 'none':
            print(f'no significant missing effect; gap {js["gap_before"]:.4g} rad')
        elif 'effects' in js:
            print(
                'missing effects: '
                + ', '.join(
                    f'{e["effect"]} = {e["value"]:.4g} ± {e["uncertainty"]:.2g} {e["unit"]}'
                    for e in js['effects']
                )
            )
            print(f'gap {js["gap_before"]:.4g} -> {js["gap_after"]:.4g} rad')
        else:
            print(
                f'missing effect: {js["effect"]} = {js["value"]:.4g} ± {js["uncertainty"]:.2g} '
                f'{js["unit"]}'
            )
            print(f'gap {js["gap_before"]:.4g} -> {js["gap_after"]:.4g} rad')
        print(f'report: {args.out}/report.md')
    return 0
