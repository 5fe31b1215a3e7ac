"""Small helpers shared by the subcommands."""
import json

from krang_model.robot import load_krang, load_wip7

ROBOTS = {'krang': load_krang, 'wip7': load_wip7}


def add_robot_argument(parser):
    parser.add_argument('--robot', choices=sorted(ROBOTS), default='krang',
                        help='robot description (default: krang, the 19-DoF Golem Krang)')


def robot_from_args(args):
    return ROBOTS[getattr(args, 'robot', 'krang')]()


def print_json(payload):
    """Machine-readable result: always the last line of stdout."""
    print(json.dumps(payload, sort_keys=False))
