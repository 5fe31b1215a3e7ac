"""How fast the simulated node set runs: sim_krang, can_bridge and adrc_controller as processes on
their udp_multicast buses, balancing, at the configured real-time factor (1: real time) and unpaced
(0: as fast as the control loop keeps up; the simulator's control-lag guard holds it within
max_control_lag_s of the last wheel command, a soft lockstep).

    .venv/bin/python bench/bench_sim_speed.py [--seconds 15] [--factors 1 0]
"""

import argparse
import os
import tempfile
import time

import rclpy
from rosgraph_msgs.msg import Clock

from krang_cli.node_set import params_files
from krang_cli.processes import NodeSet
from krang_ros.session_client import open_session_client
from krang_sim.session_config import session_devices_file


def measure(factor, seconds):
    """Simulated seconds per wall second while balancing, and the controller modes seen."""
    tmp = tempfile.mkdtemp(prefix='krang_sim_speed_')
    devices = session_devices_file(tmp)
    nodes = NodeSet(params_files(sim=True, extra=()), log_dir=os.path.join(tmp, 'logs'))
    nodes.start('sim_krang', {'devices_file': devices, 'real_time_factor': factor})
    nodes.start('can_bridge', {'devices_file': devices})
    nodes.start('adrc_controller')
    client, context = open_session_client()
    clock = []
    client.create_subscription(
        Clock,
        '/clock',
        lambda m: clock.append((time.monotonic(), m.clock.sec + m.clock.nanosec * 1e-9)),
        10,
    )
    try:
        client.enable_controller(60.0)
        client.wait_for_balance(120.0)
        client.pause(2.0)
        wall0, sim0 = clock[-1]
        modes_before = len(client.modes)
        client.pause(seconds)
        wall1, sim1 = clock[-1]
        return (sim1 - sim0) / (wall1 - wall0), sorted(set(client.modes[modes_before:]))
    finally:
        client.close()
        rclpy.try_shutdown(context=context)
        nodes.stop()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument(
        '--seconds', type=float, default=15.0, help='wall seconds measured while balancing'
    )
    parser.add_argument(
        '--factors',
        type=float,
        nargs='+',
        default=[1.0, 0.0],
        help='sim_krang real_time_factor values (0 = unpaced)',
    )
    args = parser.parse_args()
    os.environ.setdefault('ROS_DOMAIN_ID', str(130 + os.getpid() % 50))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    for factor in args.factors:
        ratio, modes = measure(factor, args.seconds)
        print(
            f'real_time_factor {factor:g}: {ratio:.2f}x real time while balancing (controller '
            f'modes: {", ".join(modes)})'
        )


if __name__ == '__main__':
    main()
