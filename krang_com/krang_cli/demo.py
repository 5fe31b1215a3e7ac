"""krang demo: the simulated Krang end to end, learning its mass model online, one
move_to_next_pose goal per pose."""

import logging
import signal
import time
from pathlib import Path

from tqdm import tqdm

from krang_bag.reader import message_counts
from krang_bag.session_report import session_figures
from krang_model.beta import load_beta, save_beta
from krang_model.robot import load_krang
from krang_model.files import write_text
from krang_ros.entry import interrupt
from krang_sim.session_config import session_devices_file, sim_rate_hz, sim_truth_file
from krang_sim.truths import generate_truth

from .bringup import start_node_set
from .composed import ComposedSimulation, CompositionError
from .node_set import STOP_ORDER
from .common import (
    add_rate_argument,
    add_sim_robot_arguments,
    print_json,
    sim_robot_overrides,
    with_rate,
)

log = logging.getLogger('krang.demo')
BETA_FILE = 'beta.yaml'  # the learned beta in the output directory


def register(subparsers):
    p = subparsers.add_parser(
        'demo',
        help='THE MAIN JOB: simulated Krang, whole node set, online learning, report',
        description='Composes sim_krang (a simulated Krang with a hidden true mass model, by '
        'default config/sim_demo_true_beta.yaml: 13 mm of forward CoM error against the '
        'nominal model) and the node set in this process, on one executor over DDS and '
        'in-process CAN buses, so that the same seed gives the same session and the same beta '
        '(--processes: a process per node instead). Records every topic to DIR/session.mcap, '
        'stands the robot up (/adrc_controller/stand_up), then sends '
        '/pose_server/move_to_next_pose a goal for '
        "each pose (adaptive selection by default: the pose that most lowers the estimator's "
        'expected forward CoM error per second) while com_estimator learns beta online '
        'from each balanced pose. Writes DIR/beta.yaml, DIR/report.md with PNG figures and '
        'DIR/logs, and prints a JSON summary.',
    )
    p.add_argument(
        '--poses',
        type=int,
        default=3,
        help='number of poses to learn from (default 3; see the README on longer sessions)',
    )
    p.add_argument('--out', default='demo_out', help='output directory (default demo_out)')
    p.add_argument(
        '--method', default='map-online', help='estimator of com_estimator (default map-online)'
    )
    p.add_argument(
        '--stand-timeout',
        type=float,
        default=120.0,
        help='s to wait for the robot to balance (simulated s; wall s with --processes)',
    )
    p.add_argument(
        '--pose-timeout',
        type=float,
        default=90.0,
        help='s to wait for each balanced pose (simulated s; wall s with --processes)',
    )
    p.add_argument(
        '--true-beta',
        metavar='FILE',
        help='the hidden truth the simulated robot has: a beta YAML/JSON, or the '
        "authors' .txt with --row (default: sim_params.yaml's true_beta, "
        'config/sim_demo_true_beta.yaml)',
    )
    p.add_argument('--row', type=int, default=None, help='row of a .txt --true-beta (from 0)')
    p.add_argument(
        '--truth-seed',
        type=int,
        default=None,
        help='instead of a file: a hidden truth drawn by krang_sim.truths (masses '
        'within 8 %%, CoMs moved up to 3 cm, forward error 12-25 mm) from this '
        'seed',
    )
    p.add_argument(
        '--seed',
        type=int,
        default=0,
        help="seed of the simulator's and CAN devices' noise (default 0)",
    )
    add_sim_robot_arguments(p)
    add_rate_argument(p)
    p.add_argument(
        '--move-points',
        type=int,
        default=None,
        metavar='N',
        help='points the controller reads on each move besides the one at rest (its '
        'move_points.per_move, default 3; 0: points at rest only; docs/learning.md, "Points '
        'read while moving")',
    )
    p.add_argument(
        '--processes',
        action='store_true',
        help='run each node in a process of its own, in lockstep with the simulator (as `krang '
        'bringup --sim`): closer to the robot, but not reproducible. By default the node set is '
        'composed in this process, and the same seed gives the same session and the same beta',
    )
    p.set_defaults(func=run)


def run(args):
    import rclpy
    from std_srvs.srv import Trigger

    from krang_ros.session_client import SessionError, open_session_client

    try:
        with_rate({}, args.rate_hz)  # a bad rate: refused before anything is written
    except ValueError as err:
        log.error('krang demo: --rate-hz %s', err)
        return 2
    if args.move_points is not None and args.move_points < 0:
        log.error('krang demo: --move-points %d: must be >= 0', args.move_points)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag = out / 'session.mcap'
    if bag.exists():
        bag.unlink()
    robot = load_krang()
    try:
        sim_robot = sim_robot_overrides(args, robot)
    except ValueError as err:
        log.error('krang demo: %s', err)
        return 2
    if args.truth_seed is not None:
        truth = generate_truth(robot, args.truth_seed)
        truth_source, true_beta, meta = truth.describe(), truth.beta, truth.meta()
    else:
        truth_source = Path(args.true_beta) if args.true_beta else sim_truth_file()
        true_beta = load_beta(truth_source, robot, row=args.row)
        meta = {'source': f'{truth_source}' + (f' row {args.row}' if args.row is not None else '')}
    truth_file = save_beta(out / 'true_beta.yaml', true_beta, robot, **meta)
    devices = str(session_devices_file(out, virtual=not args.processes))
    beta_file = str((out / BETA_FILE).resolve())
    # unpaced: the simulator runs in lockstep with the control path, as fast as it answers
    overrides = with_rate(
        {
            'sim_krang': {
                'devices_file': devices,
                'seed': args.seed,
                'real_time_factor': 0.0,
                'true_beta': str(Path(truth_file).resolve()),
                **sim_robot,
            },
            'can_bridge': {'devices_file': devices},
            'com_estimator': {'output': beta_file, 'method': args.method},
            'adrc_controller': {}
            if args.move_points is None
            else {'move_points.per_move': args.move_points},
        },
        args.rate_hz,
    )
    sigint = signal.signal(signal.SIGINT, interrupt)  # Ctrl-C: the report says so (below)
    started = time.monotonic()
    client = context = nodes = composed = None
    learned = 0
    failure = None
    try:
        if args.processes:
            nodes = start_node_set(
                sim=True, record=str(bag), log_dir=out / 'logs', overrides=overrides
            )
            client, context = open_session_client()
        else:
            composed = ComposedSimulation(overrides, record=bag, log_dir=out / 'logs')
            client = composed.session_client()
        message = client.enable_controller(timeout=60.0)
        log.info(
            'adrc_controller: %s; waiting for the simulated robot to stand up and balance ...',
            message,
        )
        client.wait_for_balance(args.stand_timeout)
        with tqdm(total=args.poses, desc='online session', unit='pose') as bar:
            for _ in range(args.poses):
                message = client.learn_next_pose(args.pose_timeout)
                learned += 1
                bar.set_postfix_str(message)
                bar.update()
        client.call(client.save, Trigger.Request())
    except (SessionError, CompositionError) as err:
        failure = str(err)
        log.error('session stopped early: %s (node logs in %s)', failure, out / 'logs')
    except KeyboardInterrupt:
        failure = 'interrupted (Ctrl-C)'
        log.error('session stopped early: %s', failure)
    finally:
        if client is not None:
            client.close()
        if context is not None:
            rclpy.try_shutdown(context=context)
        if nodes is not None:
            nodes.stop(STOP_ORDER)
        if composed is not None:
            composed.close()
        signal.signal(signal.SIGINT, sigint)
    wall = time.monotonic() - started
    # the curve starts from com_estimator's initial beta, which the demo leaves at the URDF's
    (curve, lateral), figures = session_figures(bag, robot, true_beta, out, robot.nominal_beta)
    result = {
        'poses': learned,
        'com_error_before_m': float(curve[0]),
        'com_error_after_m': float(curve[-1]),
        'true_beta': str(truth_source),
        'true_beta_row': args.row,
        'seed': args.seed,
        'rate_hz': args.rate_hz or sim_rate_hz(),
        'bag': str(bag),
    }
    write_report(out, result, curve, lateral, figures, message_counts(bag), wall, args, failure)
    print(
        f'{learned} poses learned in {wall:.0f} s: mean forward CoM error {1000 * curve[0]:.1f} '
        f'mm -> {1000 * curve[-1]:.1f} mm; report {out / "report.md"}'
    )
    print_json(result)
    return 0 if failure is None else 1


def write_report(out, result, curve, lateral, figures, counts, wall, args, failure):
    lines = [
        '# krang demo: online CoM learning on the simulated Krang',
        '',
        f'- poses learned: {result["poses"]} of {args.poses} (estimator `{args.method}`), '
        f'wall time {wall:.0f} s',
        f'- hidden truth: `{result["true_beta"]}`'
        + (f' row {result["true_beta_row"]}' if result['true_beta_row'] is not None else '')
        + f' (copied to `true_beta.yaml`); simulator seed {result["seed"]}',
        f"- sample and control rate: {result['rate_hz']:g} Hz (the robot's: 500 Hz)",
        "- mean forward CoM error (the paper's |x_com| at the true balance pitch) against "
        'the hidden true model, over 2000 held-out configurations: '
        f'**{1000 * result["com_error_before_m"]:.2f} mm before, '
        f'{1000 * result["com_error_after_m"]:.2f} mm after**',
        f'- mean sideways CoM error: {1000 * lateral[0]:.2f} mm before, '
        f'{1000 * lateral[-1]:.2f} mm after. A robot that balances in pitch never observes '
        'it: it stays where the prior put it.',
        (
            f'- learned beta: `{BETA_FILE}`'
            if (out / BETA_FILE).exists()
            else '- learned beta: none (no pose was learned, nothing was saved)'
        )
        + f'; bag: `{Path(result["bag"]).name}` ({sum(counts.values())} messages)',
        '',
    ]
    if failure:
        lines += [f'**The session stopped early:** {failure}. Node logs are in `logs/`.', '']
    lines += ['| poses | forward CoM error (mm) | sideways (mm) |', '|---|---|---|']
    lines += [
        f'| {k} | {1000 * e:.2f} | {1000 * y:.2f} |'
        for k, (e, y) in enumerate(zip(curve, lateral))
    ]
    lines += ['', '| topic | messages |', '|---|---|']
    lines += [f'| `{t}` | {n} |' for t, n in sorted(counts.items())]
    lines += [''] + [f'![{p.stem}]({p.name})' for p in figures]
    write_text(out / 'report.md', '\n'.join(lines) + '\n')
