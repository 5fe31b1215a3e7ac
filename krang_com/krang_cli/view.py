"""krang view: the robot live in Foxglove (krang_ros.foxglove_view describes the channels)."""

import argparse

DEFAULT_PORT = 8765  # foxglove_bridge's and the Foxglove app's default

DESCRIPTION = """\
Serve the running robot (real or simulated: whatever publishes /joint_states, /imu/data and the
estimator's topics on this ROS graph) to Foxglove over a WebSocket on localhost. In the Foxglove
app: Open connection -> Foxglove WebSocket -> ws://localhost:PORT. You see the robot's body posed
by its measured joints and pitch (3D panel, topics /robot and /transforms), the CoM of the
estimated and of the nominal mass model over the axle (/com), the live CoM offset (/com_live),
beta's learning curve, one point per learned balanced pose (/learning) and the controller's mode
(/mode). Ctrl-C stops it.
"""


def register(subparsers):
    p = subparsers.add_parser(
        'view',
        help='serve the robot live to Foxglove (WebSocket)',
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        '--port', type=int, default=DEFAULT_PORT, help=f'WebSocket port (default {DEFAULT_PORT})'
    )
    p.add_argument(
        '--host',
        default='127.0.0.1',
        help='address to listen on (default 127.0.0.1: this computer only)',
    )
    p.add_argument(
        '--rate',
        type=float,
        default=20.0,
        metavar='HZ',
        help='how often the pose and the CoM are sent (default 20 Hz)',
    )
    p.set_defaults(func=run)


def run(args):
    if args.rate <= 0:
        raise ValueError(f'--rate must be positive, got {args.rate}')
    # imported here: rclpy, pinocchio and foxglove would slow every other `krang` command
    from krang_ros.spin import run_node
    from krang_ros.view_node import LiveViewNode

    return run_node(lambda: LiveViewNode(args.port, args.host, args.rate), ['krang'])
