"""krang bringup: start the node set (with the simulated robot under --sim) until Ctrl-C."""
import logging

from krang_model.config import config_path

from .processes import NodeSet, wait_forever

log = logging.getLogger('krang.bringup')

ROBOT_NODES = ('can_bridge', 'adrc_controller', 'pose_server', 'com_estimator')
STOP_ORDER = ('pose_server', 'adrc_controller', 'com_estimator', 'can_bridge', 'sim_krang', 'mcap_recorder')


def register(subparsers):
    p = subparsers.add_parser(
        'bringup', help='start the node set (real robot, or --sim)',
        description='Starts can_bridge, adrc_controller, pose_server and com_estimator as processes '
                    '(and sim_krang with --sim, mcap_recorder with --record), with parameters from '
                    'config/krang_params.yaml plus --params files. Without --sim the bridge talks to the '
                    'CAN buses of config/can_devices_robot.yaml (socketcan). Ctrl-C stops everything '
                    'cleanly, the recorder last.')
    p.add_argument('--sim', action='store_true', help='start sim_krang and use the simulated buses')
    p.add_argument('--params', action='append', default=[], metavar='FILE',
                   help='extra ROS parameter YAML (node_name: ros__parameters: ...); may repeat, later wins')
    p.add_argument('--record', metavar='BAG', help='record every topic to this MCAP file')
    p.add_argument('--log-dir', help='write each node\'s output to DIR/<node>.log instead of the terminal')
    p.set_defaults(func=run)


def params_files(sim, extra):
    files = [config_path('controller.yaml'), config_path('krang_params.yaml')]  # later files win
    if sim:
        files.append(config_path('sim_params.yaml'))
    return files + list(extra)


def start_node_set(sim, extra_params=(), record=None, log_dir=None, env=None, overrides=None):
    """Start the nodes; `overrides` maps node -> {param: value} given on the command line."""
    overrides = overrides or {}
    nodes = NodeSet(params_files(sim, extra_params), log_dir=log_dir, env=env)
    if record:
        nodes.start('mcap_recorder', {'output': record, **overrides.get('mcap_recorder', {})})
    if sim:
        nodes.start('sim_krang', overrides.get('sim_krang'))
    for name in ROBOT_NODES:
        nodes.start(name, overrides.get(name))
    return nodes


def run(args):
    overrides = {} if args.sim else {'can_bridge': {'devices_file': config_path('can_devices_robot.yaml')}}
    nodes = start_node_set(args.sim, args.params, args.record, args.log_dir, overrides=overrides)
    try:
        code = wait_forever(nodes)
    finally:
        nodes.stop(STOP_ORDER)
    return code
