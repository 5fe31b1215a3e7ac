"""krang bringup: start the node set (with the simulated robot under --sim) until Ctrl-C."""

import logging
from pathlib import Path

from .node_set import RECORDER, SIM_NODE, STOP_ORDER, node_set, params_files
from .processes import NodeSet, wait_forever

log = logging.getLogger('krang.bringup')


def register(subparsers):
    p = subparsers.add_parser(
        'bringup',
        help='start the node set (real robot, or --sim)',
        description='Starts can_bridge, adrc_controller, pose_server and com_estimator as '
        'processes '
        '(and sim_krang with --sim, mcap_recorder with --record), with parameters from '
        'config/krang_params.yaml plus --params files. The bridge talks to the '
        'CAN buses of config/can_devices_robot.yaml (socketcan), with --sim to '
        'those of config/can_devices.yaml (config/sim_params.yaml). Ctrl-C stops '
        'everything '
        'cleanly, the recorder last.',
    )
    p.add_argument(
        '--sim', action='store_true', help='start sim_krang and use the simulated buses'
    )
    add_sim_robot_arguments(p, ' (with --sim)')
    p.add_argument(
        '--params',
        action='append',
        default=[],
        metavar='FILE',
        help='extra ROS parameter YAML (node_name: ros__parameters: ...); may repeat, later wins',
    )
    p.add_argument('--record', metavar='BAG', help='record every topic to this MCAP file')
    p.add_argument(
        '--log-dir', help="write each node's output to DIR/<node>.log instead of the terminal"
    )
    p.set_defaults(func=run)


def add_plant_argument(p, note=''):
    """--plant: the simulated robot's physics (None when not given: the reduced model)."""
    p.add_argument(
        '--plant',
        choices=('reduced', 'mujoco'),
        default=None,
        help="the simulated robot's physics: the controller's reduced model or the full-body "
        "MuJoCo Krang (sim_krang's `plant`; default the reduced model)" + note,
    )


def add_sim_robot_arguments(p, note=''):
    """--plant, --plant-model and --effects: the simulated robot, as sim_krang's parameters
    `plant`, `plant_model` and `effects` (`krang demo`, `krang bringup --sim`, the experiments)."""
    add_plant_argument(p, note)
    p.add_argument(
        '--plant-model',
        metavar='EXTENDED_MODEL.yaml',
        default=None,
        help='the simulated robot is the one an extended model of `krang discrepancy` describes '
        "(its effects and values; sim_krang's `plant_model`)" + note,
    )
    p.add_argument(
        '--effects',
        nargs='+',
        metavar='KEY=VALUE',
        default=None,
        help="the true robot's effects (krang_model.effects), on top of --plant-model, e.g. "
        'torque_constant=0.75 wheel_coulomb_friction=4 wheel_viscous_friction=3' + note,
    )


def sim_robot_overrides(args, robot):
    """sim_krang's parameters from --plant, --plant-model and --effects (those given). A bad
    extended model or effect raises ValueError here, in one line, before any node starts."""
    from krang_sim.plant import plant_terms

    try:
        plant_terms(robot, args.effects or (), args.plant_model)
    except (KeyError, ValueError, OSError) as err:
        raise ValueError(f'--plant-model / --effects: {err}') from None
    overrides = {}
    if args.plant:
        overrides['plant'] = args.plant
    if args.plant_model:
        overrides['plant_model'] = str(Path(args.plant_model).resolve())
    if args.effects:
        overrides['effects'] = list(args.effects)
    return overrides


def start_node_set(sim, extra_params=(), record=None, log_dir=None, env=None, overrides=None):
    """Start the nodes; `overrides` maps node -> {param: value} given on the command line."""
    overrides = dict(overrides or {})
    if record:
        overrides[RECORDER] = {'output': record, **overrides.get(RECORDER, {})}
    nodes = NodeSet(params_files(sim, extra_params), log_dir=log_dir, env=env)
    for spec in node_set(sim, bool(record), extra_params):
        nodes.start(spec.executable, overrides.get(spec.executable))
    return nodes


def run(args):
    overrides = {}
    if args.plant or args.plant_model or args.effects:
        if not args.sim:
            log.error('krang bringup: --plant, --plant-model and --effects need --sim')
            return 2
        from krang_model.robot import load_krang

        try:
            overrides[SIM_NODE] = sim_robot_overrides(args, load_krang())
        except ValueError as err:
            log.error('krang bringup: %s', err)
            return 2
    nodes = start_node_set(args.sim, args.params, args.record, args.log_dir, overrides=overrides)
    try:
        code = wait_forever(nodes)
    finally:
        nodes.stop(STOP_ORDER)
    return code
