"""How fast the simulated node set runs while balancing: sim_krang, can_bridge and adrc_controller
as processes on their udp_multicast buses, in lockstep (krang_sim/node.py: the physics waits for
the wheel command that answers each sample), at the configured real-time factor (1: real time) and
unpaced (0: as fast as the control path answers); then the same three nodes composed in this
process as `krang demo` runs them (krang_cli/composed.py), with its ratio to the unpaced processes.
Also prints the lockstep's waits and misses and the wall time per sample. `--plant` picks the
simulated robot's physics (sim_krang's `plant`): the controller's reduced model or the full-body
MuJoCo Krang.

    .venv/bin/python bench/bench_sim_speed.py [--seconds 15] [--factors 1 0] [--rate-hz 500]
        [--plant reduced|mujoco]
"""

import argparse
import os
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rosgraph_msgs.msg import Clock

from krang_cli.common import add_plant_argument
from krang_cli.composed import ComposedSimulation
from krang_cli.node_set import params_files
from krang_cli.processes import NodeSet, WorkingDir
from krang_core import names
from krang_ros import topics
from krang_ros.session_client import open_session_client
from krang_ros.spin import Polled, take_latest
from krang_sim.session_config import rate_overrides, session_devices_file, sim_rate_hz


def node_overrides(rate_hz, plant):
    """Per node: the parameters that put the sample and control rate at `rate_hz` (None: the
    configured one; krang_sim.session_config.rate_overrides) and sim_krang's physics at
    `plant`."""
    rates = rate_overrides(rate_hz)
    return (
        {'plant': plant, **rates.get('sim_krang', {})},
        rates.get('can_bridge', {}),
        rates.get('adrc_controller', {}),
    )


def measure(tmp, factor, seconds, rate_hz=None, plant='reduced'):
    """Simulated seconds per wall second while balancing, and sim_krang's figures: lockstep
    misses, seconds waiting for the answer per wall second, real-time slips (paced, each a stall
    of more than its max_lag_s that the simulated time gave up) (node logs under `tmp`)."""
    devices = session_devices_file(tmp)
    sim, bridge, controller = node_overrides(rate_hz, plant)
    nodes = NodeSet(params_files(sim=True, extra=()), log_dir=os.path.join(tmp, 'logs'))
    nodes.start('sim_krang', {'devices_file': devices, 'real_time_factor': factor, **sim})
    nodes.start('can_bridge', {'devices_file': devices, **bridge})
    nodes.start('adrc_controller', controller)
    client, context = open_session_client()
    diag = {}
    # read at the window's ends only (take_latest): a wake per sample would load the 2 cores too
    clock_sub = client.create_subscription(
        Clock, names.CLOCK, lambda m: None, topics.QOS[names.CLOCK], callback_group=Polled()
    )

    def clock_now(timeout=5.0):
        """(wall, simulated) time at the next /clock message (one already waiting is old)."""
        take_latest(clock_sub)
        deadline = time.monotonic() + timeout
        while (msg := take_latest(clock_sub)) is None:
            if time.monotonic() > deadline:
                raise RuntimeError(f'no /clock for {timeout:g} s: is sim_krang running?')
            time.sleep(0.0005)
        return time.monotonic(), msg.clock.sec + msg.clock.nanosec * 1e-9

    def on_diag(msg):
        for s in msg.status:
            diag[s.name] = {kv.key: kv.value for kv in s.values}

    client.create_subscription(DiagnosticArray, names.DIAGNOSTICS, on_diag, 50)
    try:
        client.enable_controller(60.0)
        client.wait_for_balance(120.0)
        client.pause(2.0)
        wall0, sim0 = clock_now()
        before = dict(diag.get('sim_krang', {}))
        client.pause(seconds)
        wall1, sim1 = clock_now()
        after = diag.get('sim_krang', {})
        ratio = (sim1 - sim0) / (wall1 - wall0)
        misses = int(after.get('lockstep_misses', 0)) - int(before.get('lockstep_misses', 0))
        waited = float(after.get('lockstep_wait_s', 0)) - float(before.get('lockstep_wait_s', 0))
        slips = int(after.get('real_time_slips', 0)) - int(before.get('real_time_slips', 0))
        return ratio, misses, waited / (wall1 - wall0), slips, client.mode
    finally:
        client.close()
        rclpy.try_shutdown(context=context)
        nodes.stop()


def measure_composed(tmp, seconds, rate_hz=None, plant='reduced'):
    """Simulated seconds per wall second while balancing, composed (no recorder, pose server and
    estimator idle; node logs under `tmp`)."""
    devices = str(session_devices_file(tmp, virtual=True))
    sim, bridge, controller = node_overrides(rate_hz, plant)
    composed = ComposedSimulation(
        {
            'sim_krang': {'devices_file': devices, **sim},
            'can_bridge': {'devices_file': devices, **bridge},
            'adrc_controller': controller,
        },
        log_dir=os.path.join(tmp, 'logs'),
    )
    try:
        client = composed.session_client()
        client.enable_controller(60.0)
        client.wait_for_balance(120.0)
        client.pause(2.0)
        wall0, sim0 = time.monotonic(), composed.sim_time
        while time.monotonic() - wall0 < seconds:
            composed.advance()
        ratio = (composed.sim_time - sim0) / (time.monotonic() - wall0)
        return ratio, client.mode
    finally:
        composed.close()


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
    parser.add_argument(
        '--rate-hz',
        type=float,
        default=None,
        help=f'sample and control rate (default: config/sim_params.yaml, {sim_rate_hz():g} Hz)',
    )
    add_plant_argument(parser)
    args = parser.parse_args()
    os.environ.setdefault('ROS_DOMAIN_ID', str(130 + os.getpid() % 50))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rate = args.rate_hz or sim_rate_hz()
    plant = args.plant or 'reduced'
    unpaced = None
    for factor in args.factors:
        with WorkingDir('krang_sim_speed_') as work:
            ratio, misses, waiting, slips, mode = measure(
                work.path, factor, args.seconds, args.rate_hz, plant
            )
        unpaced = ratio if factor == 0 else unpaced
        print(
            f'processes, real_time_factor {factor:g}: {ratio:.2f}x real time while balancing at '
            f'{rate:g} Hz on the {plant} plant (mode {mode}; {1e3 / (ratio * rate):.2f} ms wall '
            f'per sample, of which {1e3 * waiting / (ratio * rate):.2f} ms waiting for the '
            f'answer; lockstep misses {misses}'
            + (f', real-time slips {slips})' if factor > 0 else ')'),
            flush=True,
        )
    with WorkingDir('krang_sim_speed_') as work:
        ratio, mode = measure_composed(work.path, args.seconds, args.rate_hz, plant)
    against = f', {ratio / unpaced:.2f}x the unpaced processes' if unpaced else ''
    print(
        f'composed: {ratio:.2f}x real time while balancing at {rate:g} Hz on the {plant} plant '
        f'(mode {mode}; {1e3 / (ratio * rate):.2f} ms wall per sample{against})'
    )


if __name__ == '__main__':
    main()
