"""krang bringup: start the node set (with the simulated robot under --sim) until Ctrl-C."""

import logging

from .common import add_rate_argument, add_sim_robot_arguments, sim_robot_overrides, with_rate
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
    add_rate_argument(p, ' (with --sim)')
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
    robot_options = args.plant or args.plant_model or args.effects
    if (robot_options or args.rate_hz is not None) and not args.sim:
        log.error('krang bringup: --plant, --plant-model, --effects and --rate-hz need --sim')
        return 2
    try:
        overrides = with_rate({}, args.rate_hz)
    except ValueError as err:
        log.error('krang bringup: --rate-hz %s', err)
        return 2
    if robot_options:
        from krang_model.robot import load_krang

        try:
            robot = sim_robot_overrides(args, load_krang())
        except ValueError as err:
            log.error('krang bringup: %s', err)
            return 2
        overrides[SIM_NODE] = {**overrides.get(SIM_NODE, {}), **robot}
    nodes = start_node_set(args.sim, args.params, args.record, args.log_dir, overrides=overrides)
    try:
        code = wait_forever(nodes)
    finally:
        nodes.stop(STOP_ORDER)
    return code
