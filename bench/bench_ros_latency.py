"""Latency from a sensor frame on the CAN bus to the wheel-command frame on the bus, through
can_bridge and adrc_controller (real processes, DDS, udp_multicast CAN), and the control rate.

--robot: the robot's configuration. Wall clock, no simulator, the robot's parameter files
(krang_cli.node_set.params_files(sim=False)) with the device map on private udp_multicast ports,
DMU samples and the controller's rate_hz at --rate-hz (500) by parameter, plus
CONTROLLER_OVERRIDES below. Two processes play the devices (bench/device_player.py --play dmu:
the DMU; --play rest: the AMC start-up and TPDOs at the timer cycle the bridge writes to the
drives, the device map's wheels.tpdo_period_ms or --tpdo-period-ms, their phase in the sample
period drifting by --tpdo-drift-ppm as free-running clocks do, the PowerCube modules), their
periodic frames spaced as a bus at --bus-bitrate (1 Mbit/s, Krang's) carries them; the robot
sits, the controller is enabled and asked to stand up, the players pitch the robot up to the
nominal balance pitch and hold it there quietly (white sensor noise, no physics), the controller
goes through STAND_UP to BALANCE by its own mode machine, and the measurement runs while it
balances.
In the same run, before the nodes start, the bare reference chain (bench/ref_chain.py: CAN ->
process 1 -> topic -> process 2 -> topic -> process 1 -> CAN, SingleThreadedExecutor) is played
at the same rate for as long, with the player playing the devices all the while (the TPDO sets
too, from stand-in drives, as the drives are not started yet): each chain runs alone beside the
same player. Run together, each chain's CPU
was the other's load (on 2 cores the reference takes half a core), a load the robot does not
have. --load N adds N busy-loop processes during both measurements.

Matching a wheel command to its sample: every 5th DMU sample is a probe (a 0.03 rad/s step of the
pitch rate, taken back over the next 4 samples, alternating in sign); its answer is the first
current RPDO after the probe frame that moves with it by more than half the probes' response, so
it is found even when it comes after the next samples (up to two probe spacings, 20 ms; a later
answer counts as none). p50/p99 are the answered probes' latencies; a probe never answered is a
sample that never reached the wheels (overwritten by a newer one). The timing match (the first new
RPDO after a sample frame) is printed too: it cannot tell an answer later than the next sample from
that sample's own, so it reads short when the latency nears the sample period. An RPDO that repeats
the drive's previous payload is the bridge's periodic refresh, not an answer (the noise makes every
answer differ). Times are kernel receive stamps on the player's socket: the bus as the devices
see it. The p50 is also given by where the drives' next TPDO set came after the sample (fifths
of the period, `p50_by_next_tpdo_ms`, the reference's alike): the phase sweeps the period, and the
latency depends on it (docs/performance.md, the control path's tables).

The control rate (`rate_hz`) is the controller's own count of steps on new samples
(`samples_stepped` in its diagnostics) per second of its clock across the window; a sample
stepped while a newer one waited sends no command (`samples_superseded`, printed as a rate
too). The bus gives two cross-checks: the new RPDOs per second, and those that follow distinct
samples by timing alone (the newest sample before each), which undercounts as soon as two
answers fall between two samples, i.e. whenever the latency jitters around the sample period.
Along the path: the DMU samples the player played (it plays a period it was late for late, in
order, as a device's transmit queue would; how many went out over a period late is printed) and
the /imu/data samples can_bridge published (its diagnostics' count).
Scheduling: can_bridge and adrc_controller run under SCHED_FIFO at the robot's
`thread_priority` (config/krang_params.yaml, 40; krang_ros/realtime.py), the reference chain alike
(a fair reference runs as the nodes run), and the device players PLAYER_PRIORITY_ABOVE higher
(the DMU's one more), both on one CPU (players_setup; they stand in for devices that have their
own processors), where permitted. --thread-priority N sets
the nodes' and the chain's priority instead; 0 puts every process on the default scheduler (then,
with --load, the measurement is not valid: starved, the player missed its periods and the
controller stopped on stale data).

Default (no --robot): the simulated node set's parameters (config/sim_params.yaml) on wall time,
the robot sitting, the wheel velocity toggled every 0.5 s: the first current frame that changes
after a toggle ends the path (in SIT the ground PD commands -10 A per rad/s; ros_latency_sim.py).
The figures are computed by ros_latency_analysis.py.

--trace splits each sample's latency into its segments (krang_ros/trace.py: the nodes write the
time each sample passes each stage; joined on the sample's stamp, which the wheel command
carries back): how long the bridge takes to receive the frame, to decode, filter and publish it,
DDS to the controller, its step, DDS back, and the bridge's encoding and sending.

    .venv/bin/python bench/bench_ros_latency.py --robot [--seconds 20] [--load 2] [--json]
        [--thread-priority N] [--trace] [--tpdo-phase F --tpdo-drift-ppm 0] [--bus-bitrate 0]
    .venv/bin/python bench/bench_ros_latency.py [--seconds 20]
"""

import argparse
import glob
import json
import os
import select
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from std_srvs.srv import SetBool

from krang_can_bridge.config import CAN_BITRATE, ConfigError, load_devices
from krang_cli.node_set import file_parameter, params_files
from krang_cli.processes import NodeSet, WorkingDir, child_setup, is_real_time
from krang_core import names
from krang_ros import trace
from krang_ros.session_client import SessionError, open_session_client
from krang_sim.session_config import private_port, session_devices_file
from ros_latency_analysis import (
    JSON_KEYS,
    analyse,
)
from ros_latency_sim import run_sim_params

BENCH = Path(__file__).resolve().parent
#: The controller's parameters that differ from the robot's here. Without physics a command has
#: no effect: the ESO reads that as a disturbance and winds the current up to its clamp, where
#: every answer is the same frame, so BALANCE runs the LQR law the ADRC wraps (the observers still
#: run: the same computation). And the machine running the benchmark is loaded by design (--load):
#: a stall of 0.1 s (the robot's stale timeout) or 0.5 s (the simulator's), seen on the shared
#: 2-core box, ends the measurement in SAFE_STOP, where every command is zero; 2 s rides it out.
CONTROLLER_OVERRIDES = {'adrc.use_disturbance_rejection': False, 'safety.stale_timeout_s': 2.0}
PLAYER_PRIORITY_ABOVE = 10  # SCHED_FIFO: the devices above the nodes
#: The drives' and the DMU's clocks are free-running crystals (50 ppm each, typically): the
#: TPDOs' phase in the sample period drifts, and the latency depends on it (docs/architecture.md,
#: "The latency benchmark"): at 100 ppm and 2 ms a 20 s measurement sees every phase once.
DRIFT_PPM = 100.0
#: Krang's CAN nets: the players space their frames by their time on this wire
#: (device_player.Wire); in one burst the drives' eight TPDO frames came twice as fast as any bus
#: carries them, and the bridge read them in one stretch.
BUS_BITRATE = float(CAN_BITRATE)


# ---- --robot: the run ---------------------------------------------------------------------------
def _start(cmd, log_dir, name, **kwargs):
    log = open(os.path.join(log_dir, f'{name}.log'), 'w')
    return subprocess.Popen(cmd, stdout=kwargs.pop('stdout', log), stderr=log, **kwargs), log


def _stop(proc, timeout=5.0):
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def bring_to_balance(client, tell, timeout, dead=dict):
    """Enable the controller, ask it to stand once it sits with fresh data, start the player's
    stand-up ramp when it enters STAND_UP, until it balances. A fall back to SAFE_STOP (stale data
    on a loaded machine) starts over from sitting. `dead()`: the nodes that exited."""
    deadline = time.monotonic() + timeout
    ramp = False
    reply = None
    while client.mode != 'balance':
        if dead():
            raise SessionError(f'node(s) exited: {dead()}')
        if time.monotonic() > deadline:
            raise SessionError(
                f'no BALANCE within {timeout:.0f} s (modes seen: {client.modes}; '
                f'last reply: {reply.message if reply else None})'
            )
        mode = client.mode
        if mode in (None, 'safe_stop'):
            if ramp:
                tell('sit')
                ramp = False
            reply = client.call(
                client.enable,
                SetBool.Request(data=True),
                timeout=max(1.0, deadline - time.monotonic()),
            )
            client.pause(1.0)
        elif mode == 'sit':
            client.pause(1.0)  # the controller's pose from complete joint states
            if client.mode == 'sit':
                reply = client.stand_up()
                client.pause(0.2)
        elif mode == 'stand_up' and not ramp:
            tell('stand')
            ramp = True
        else:
            client.pause(0.05)


def run_robot(seconds, rate_hz, load, **options):
    """`measure_robot` (`options`: its keywords) in a working directory (logs, the player's
    record, the trace) removed after a valid run and kept, and named, otherwise."""
    with WorkingDir('krang_latency_') as work:
        fig = measure_robot(work.path, seconds, rate_hz, load, **options)
        if fig['left_balance']:
            work.keep('NOT VALID (the controller left BALANCE)')
        return fig


def players_setup(priority):
    """The device players' preexec_fn: `child_setup(priority)`, on one CPU. The devices have
    processors of their own; here the players get one of the two cores, and the DMU's, a priority
    above the other's, is never late behind the drives' work. On both cores at once (two
    processes above the nodes), their bursts starved the nodes: p50 1.87-2.52 ms against 1.33-1.43
    with the drives' player below the nodes (which then played only 467-469 TPDO sets a second)."""
    setup = child_setup(priority)

    def apply():
        setup()
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    return apply


def measure_robot(
    tmp,
    seconds,
    rate_hz,
    load,
    tpdo_period_ms=None,
    tpdo_phase=0.5,
    priority=None,
    traced=False,
    tpdo_drift_ppm=DRIFT_PPM,
    bitrate=BUS_BITRATE,
):
    """Start the player; measure the reference chain alone for `seconds`, then the node set for
    `seconds` while the controller balances, each with `load` busy loops; return the figures of
    `analyse`. `tpdo_period_ms`: the drives' TPDO timer (default: the device map's);
    `tpdo_phase`: where in the sample period their TPDOs come at first, `tpdo_drift_ppm`: how
    much slower their timer runs than the DMU's, `bitrate`: the buses' bit rate, which spaces the
    players' frames (device_player.py). `priority`:
    the nodes' and the reference chain's SCHED_FIFO priority (default: the robot's
    thread_priority; 0: the default scheduler), the player's PLAYER_PRIORITY_ABOVE higher.
    `traced`: the nodes write krang_ros.trace's stage times; the figures gain `trace_p50_ms` and
    `trace_p90_ms`, each segment's percentile. Everything is written under `tmp`."""
    if priority is None:
        priority = int(file_parameter('can_bridge', 'thread_priority', sim=False, default=0))
    nodes_rt = priority
    player_rt = min(priority + PLAYER_PRIORITY_ABOVE, 99) if priority > 0 else 0
    logs = os.path.join(tmp, 'logs')
    os.makedirs(logs)
    port = private_port()
    devices_file = session_devices_file(
        tmp, port, wheels=None if tpdo_period_ms is None else {'tpdo_period_ms': tpdo_period_ms}
    )
    tpdo_period_ms = load_devices(devices_file).wheels.tpdo_period_ms
    py = sys.executable
    # the DMU in a process of its own (device_player.PLAYS), the other devices in another
    records = {play: os.path.join(tmp, f'record_{play}.npz') for play in ('dmu', 'rest')}
    children = [
        _start(
            [
                py,
                str(BENCH / 'device_player.py'),
                '--play',
                play,
                '--devices',
                str(devices_file),
                '--ref-port',
                str(port + 15),
                '--rate-hz',
                str(rate_hz),
                '--tpdo-phase',
                str(tpdo_phase),
                '--tpdo-drift-ppm',
                str(tpdo_drift_ppm),
                '--bitrate',
                str(bitrate),
                '--out',
                out,
            ],
            logs,
            f'device_player_{play}',
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            preexec_fn=players_setup(min(player_rt + (play == 'dmu'), 99) if player_rt else 0),
        )
        for play, out in records.items()
    ]
    players = [proc for proc, _ in children]
    busy = []
    trace_prefix = os.path.join(tmp, 'trace')
    nodes = NodeSet(
        params_files(sim=False),
        log_dir=logs,
        env=os.environ | ({trace.ENV: trace_prefix} if traced else {}),
    )
    client = context = None

    def tell(word):
        for player in players:
            if player.poll() is None:
                player.stdin.write(word + '\n')
                player.stdin.flush()

    def loaded(n):
        return [
            subprocess.Popen([py, '-c', 'while True: pass'], preexec_fn=child_setup())
            for _ in range(n)
        ]

    try:
        if any(player.stdout.readline().strip() != 'ready' for player in players):
            raise RuntimeError(f'a device player did not start (see {logs}/device_player_*.log)')
        # 1. the reference chain alone (the nodes not yet started)
        ref = [
            _start(
                [py, str(BENCH / 'ref_chain.py'), role, '--port', str(port + 15)],
                logs,
                f'ref_{role}',
                preexec_fn=child_setup(nodes_rt),
                **({'stdout': subprocess.PIPE, 'text': True} if role == 'can' else {}),
            )
            for role in ('can', 'relay')
        ]
        children += ref
        tell('ref')
        ready, _, _ = select.select([ref[0][0].stdout], [], [], 60.0)
        if not ready or ref[0][0].stdout.readline().strip() != 'answering':
            raise RuntimeError(f'the reference chain did not answer (see {logs}/ref_*.log)')
        busy = loaded(load)
        time.sleep(1.0)
        ref_window = (time.time(), None)
        time.sleep(seconds)
        ref_window = (ref_window[0], time.time())
        tell('noref')
        for proc in busy:
            _stop(proc)
        for proc, _ in ref:
            _stop(proc)
        # 2. the node set, balancing
        procs = {
            'DMU player': players[0],
            'device player': players[1],
            'can_bridge': nodes.start(
                'can_bridge', {'devices_file': devices_file, 'thread_priority': nodes_rt}
            ),
            'adrc_controller': nodes.start(
                'adrc_controller',
                CONTROLLER_OVERRIDES | {'rate_hz': rate_hz, 'thread_priority': nodes_rt},
            ),
        }
        client, context = open_session_client()
        diag = []  # the controller's (stamp, samples_stepped, samples_superseded)
        bridge_diag = []  # the bridge's (stamp, /imu/data samples published)

        def on_diag(msg):
            t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                if status.name == 'adrc_controller' and 'samples_stepped' in values:
                    counts = (int(values['samples_stepped']), int(values['samples_superseded']))
                    diag.append((t, *counts))
                elif status.name == 'can_bridge: samples published' and names.IMU in values:
                    bridge_diag.append((t, int(values[names.IMU])))

        client.create_subscription(DiagnosticArray, names.DIAGNOSTICS, on_diag, 50)
        try:
            bring_to_balance(client, tell, 180.0, nodes.dead)
        except SessionError as exc:
            raise SessionError(f'{exc} (logs in {logs})') from exc
        # the nodes set their own priority once built (their thread_priority parameter)
        rt_applied = ', '.join(name for name, p in procs.items() if is_real_time(p.pid))
        modes_before = len(client.modes)
        client.pause(1.0)  # the command noise without probes (noise_level)
        tell('probe')
        busy = loaded(load)
        client.pause(1.0)
        window = (time.time(), None)
        client.pause(seconds)
        window = (window[0], time.time())
        left_modes = sorted(set(client.modes[modes_before:]) - {'balance'})
    finally:
        for proc in busy:
            _stop(proc)
        if client is not None:
            client.close()
            rclpy.try_shutdown(context=context)
        tell('quit')
        for player in players:
            try:
                player.wait(20.0)
            except subprocess.TimeoutExpired:
                pass
        nodes.stop()
        for proc, log in children:
            _stop(proc)
            log.close()
    with np.load(records['rest']) as rest, np.load(records['dmu']) as dmu:
        # the samples from the DMU's player, the rest from the other
        record = dict(rest) | {k: dmu[k] for k in dmu.files if k.startswith('sample_')}
        fig = analyse(record, window, rate_hz, diag, ref_window, bridge_diag) | {
            'left_balance': left_modes,
            'real_time': rt_applied,
            'thread_priority': priority,
            'tpdo_period_ms': tpdo_period_ms,
            'tpdo_phase': tpdo_phase,
            'tpdo_drift_ppm': tpdo_drift_ppm,
            'bus_bitrate': bitrate,
        }
    if traced:
        fig |= trace_figures(glob.glob(f'{trace_prefix}.*'), window)
    return fig


def trace_figures(paths, window):
    """p50 and p90 [ms] of each segment of krang_ros.trace over the samples in `window`."""
    durations = trace.segments(trace.read(paths), *window)
    if not durations['total']:
        raise RuntimeError('--trace: no sample traced through every stage')
    return {
        f'trace_p{q}_ms': {k: 1e3 * float(np.percentile(v, q)) for k, v in durations.items()}
        for q in (50, 90)
    } | {'traced_samples': len(durations['total'])}


def print_robot(fig, load):
    bitrate = fig['bus_bitrate']
    frames = f'frames spaced at {bitrate / 1e6:g} Mbit/s' if bitrate else 'frames in bursts'
    print(
        f'robot configuration, wall clock, {fig["configured_rate_hz"]:.0f} Hz configured, '
        f'TPDOs every {fig["tpdo_period_ms"]} ms from phase {fig["tpdo_phase"]:.2f}, '
        f'{fig["tpdo_drift_ppm"]:g} ppm slower than the DMU, {frames}, {load} busy '
        f'loop(s), {fig["seconds"]:.1f} s balancing'
    )
    print(
        f'sensor frame -> wheel command frame (can_bridge + adrc_controller): '
        f'p50 {fig["p50_ms"]:.2f} ms, p99 {fig["p99_ms"]:.2f} ms, max {fig["max_ms"]:.2f} ms '
        f'(matched by {fig["match"]}; {fig["probes_answered"]} of {fig["probes"]} probes '
        f'answered)'
    )
    print(
        f'  by timing alone (first new RPDO after the sample): p50 {fig["timing_p50_ms"]:.2f} '
        f'ms, p99 {fig["timing_p99_ms"]:.2f} ms'
    )
    print(
        f"control rate: {fig['rate_hz']:.1f} Hz of steps on new samples (the controller's "
        f'count; {fig["superseded_hz"]:.1f}/s of them superseded by a newer sample before their '
        f'command), {fig["configured_rate_hz"]:.0f} Hz configured ({100 * fig["rate_ratio"]:.1f} '
        f'%); on the bus {fig["new_commands_hz"]:.1f} new current commands/s, '
        f'{fig["bus_rate_hz"]:.1f}/s after distinct samples by timing alone; DMU played at '
        f'{fig["dmu_rate_hz"]:.1f} Hz ({fig["dmu_late_hz"]:.1f}/s sent over a period late by '
        f'the player, up to {fig["dmu_max_late_ms"]:.1f} ms), /imu/data published by can_bridge '
        f'at {fig["bridge_imu_rate_hz"]:.1f} Hz, TPDO sets at {fig["tpdo_rate_hz"]:.1f} Hz '
        f'({fig["ref_tpdo_rate_hz"]:.1f} Hz beside the reference) in '
        f'{10 * fig["tpdo_phases_seen"]:.0f} of 10 tenths of the sample period; SCHED_FIFO: '
        f'{fig["real_time"] or "no"}'
        + (f' (nodes at {fig["thread_priority"]})' if fig['real_time'] else '')
    )
    print(
        f'reference (bare rclpy chain, same run): p50 {fig["ref_p50_ms"]:.2f} ms, '
        f'p99 {fig["ref_p99_ms"]:.2f} ms, {fig["ref_lost"]} of {fig["ref_frames"]} lost'
    )
    print(f'ratio to the reference: p50 {fig["p50_ratio"]:.2f}x, p99 {fig["p99_ratio"]:.2f}x')
    ours, ref = fig['p50_by_next_tpdo_ms'], fig['ref_p50_by_next_tpdo_ms']
    part = 1e3 / fig['configured_rate_hz'] / len(ours)
    print(
        "p50 by when the drives' next TPDO set came after the sample (reference's in brackets): "
        + ', '.join(
            f'{k * part:.1f}-{(k + 1) * part:.1f} ms after: {a:.2f} ({b:.2f})'
            for k, (a, b) in enumerate(zip(ours, ref))
        )
    )
    if 'trace_p50_ms' in fig:
        print(
            f"where the time goes (--trace, {fig['traced_samples']} samples; the frame's kernel "
            'stamp in the bridge to its current frames sent):'
        )
        for name, p50 in fig['trace_p50_ms'].items():
            print(f'  {name:36s} p50 {p50:6.3f} ms  p90 {fig["trace_p90_ms"][name]:6.3f} ms')
    if fig['left_balance']:
        print(
            f'NOT VALID: the controller left BALANCE during the measurement '
            f'({", ".join(fig["left_balance"])}): the figures mix in its zero commands'
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument(
        '--robot',
        action='store_true',
        help="the robot's configuration (default: the simulated node set's)",
    )
    parser.add_argument('--seconds', type=float, default=20.0, help='measured seconds')
    parser.add_argument(
        '--rate-hz',
        type=float,
        default=500.0,
        help='--robot: DMU sample rate and the controller rate_hz',
    )
    parser.add_argument(
        '--tpdo-period-ms',
        type=int,
        help="--robot: the drives' TPDO timer in ms (default: the device map's "
        'wheels.tpdo_period_ms, 2)',
    )
    parser.add_argument(
        '--tpdo-phase',
        type=float,
        default=0.5,
        help='--robot: the TPDO sets this fraction of a sample period after each DMU sample, '
        'at first (free-running drives come at any phase)',
    )
    parser.add_argument(
        '--tpdo-drift-ppm',
        type=float,
        default=DRIFT_PPM,
        help="--robot: the drives' TPDO timer this many ppm slower than the DMU's clock, so that "
        'their phase sweeps the sample period as free-running clocks do (100: once in 20 s at '
        '2 ms; 0: a fixed phase)',
    )
    parser.add_argument(
        '--bus-bitrate',
        type=float,
        default=BUS_BITRATE,
        help="--robot: the CAN buses' bit rate, at which the device players space their "
        'periodic frames as the wire does (0: in bursts, as a udp_multicast socket takes them)',
    )
    parser.add_argument(
        '--load', type=int, default=0, help='--robot: busy-loop processes during the measurement'
    )
    parser.add_argument(
        '--thread-priority',
        type=int,
        help="--robot: the nodes' and the reference chain's SCHED_FIFO priority, the device "
        f"player's {PLAYER_PRIORITY_ABOVE} higher (default: the robot's thread_priority, "
        'config/krang_params.yaml; 0: every process on the default scheduler)',
    )
    parser.add_argument(
        '--trace',
        action='store_true',
        help='--robot: the nodes record when each sample passes each stage (krang_ros/trace.py) '
        'and the figures split the latency into its segments',
    )
    parser.add_argument(
        '--json', action='store_true', help='--robot: print the figures as JSON on the last line'
    )
    args = parser.parse_args()
    os.environ.setdefault('ROS_DOMAIN_ID', str(180 + os.getpid() % 50))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    if not args.robot:
        run_sim_params(args.seconds)
        return
    if not 0.0 <= args.tpdo_phase < 1.0:
        parser.error('--tpdo-phase must be in [0, 1)')
    if args.thread_priority is not None and not 0 <= args.thread_priority <= 99:
        parser.error('--thread-priority must be 0 (the default scheduler) to 99')
    try:
        fig = run_robot(
            args.seconds,
            args.rate_hz,
            args.load,
            tpdo_period_ms=args.tpdo_period_ms,
            tpdo_phase=args.tpdo_phase,
            priority=args.thread_priority,
            traced=args.trace,
            tpdo_drift_ppm=args.tpdo_drift_ppm,
            bitrate=args.bus_bitrate,
        )
    except ConfigError as exc:  # the session map with --tpdo-period-ms, checked before any start
        parser.error(str(exc))
    print_robot(fig, args.load)
    if args.json:
        print(
            json.dumps(
                {k: fig[k] for k in JSON_KEYS}
                | {k: v for k, v in fig.items() if k not in JSON_KEYS}
            )
        )


if __name__ == '__main__':
    main()
