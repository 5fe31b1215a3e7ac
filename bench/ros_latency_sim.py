"""bench_ros_latency.py's default mode: the simulated node set's parameters
(config/sim_params.yaml) on wall time, the robot sitting, the wheel velocity toggled every 0.5 s:
the first current frame that changes after a toggle ends the path (in SIT the ground PD commands
-10 A per rad/s)."""

import importlib
import os
import threading
import time

import can
import numpy as np
import rclpy
from std_srvs.srv import SetBool

from krang_can_bridge.config import load_devices
from krang_can_bridge.protocols import load_dbc
from krang_can_bridge.protocols.amc import AmcDriveCodec
from krang_cli.node_set import params_files
from krang_cli.processes import NodeSet, WorkingDir
from krang_core import names
from krang_model.drivetrain import drivetrain
from krang_model.robot import load_krang
from krang_ros import topics
from krang_ros.session_client import SessionError, open_session_client
from krang_sim.devices import KrangCanDevices
from krang_sim.session_config import session_devices_file


def run_sim_params(seconds):
    """`measure_sim_params` in a working directory removed after the run (kept if it fails)."""
    with WorkingDir('krang_latency_') as work:
        measure_sim_params(work.path, seconds)


def measure_sim_params(tmp, seconds):
    """The robot sitting, the wheel velocity toggled every 0.5 s (see the module docstring)."""
    robot = load_krang()
    devices_file = session_devices_file(tmp)
    config = load_devices(devices_file)
    joints = dict(zip(robot.pose_joints, [2.46] + [0.0] * 15))
    devices = KrangCanDevices(config, initial_joint_positions=joints)
    left = config.wheels.drive('JLWheel')
    codec = AmcDriveCodec(left, config.wheels, load_dbc(config.dbc_path))
    buses = {name: can.Bus(**config.buses[name].bus_kwargs()) for name in config.buses_in_use()}
    lock = threading.Lock()
    currents = []  # (time, amps) of the left current RPDO frames

    class Devices(can.Listener):
        def __init__(self, name):
            self.name = name

        def on_message_received(self, msg):
            now = time.perf_counter()
            if msg.arbitration_id in codec.command_ids:
                try:
                    currents.append((now, codec.decode_current_command(msg)[1]))
                except Exception:  # noqa: BLE001 - not the current RPDO
                    pass
            with lock:
                replies = devices.on_frame(self.name, msg)
            for reply in replies:
                buses[reply.bus].send(reply.msg)

    notifiers = [can.Notifier(bus, [Devices(name)], timeout=0.05) for name, bus in buses.items()]

    # the simulated node set's parameters, but on wall time: this benchmark plays the robot, with
    # no /clock
    nodes = NodeSet(params_files(True, []), log_dir=os.path.join(tmp, 'logs'))
    nodes.start('can_bridge', {'devices_file': devices_file, 'use_sim_time': False})
    nodes.start('adrc_controller', {'modes.auto_stand': False, 'use_sim_time': False})
    toggles = []
    efforts = []
    stop = threading.Event()

    sit = drivetrain(load_krang()).caster_contact_pitch  # on the caster, the axle at rest

    def robot_loop():
        velocity, next_toggle = 0.0, time.perf_counter() + 3.0
        while not stop.is_set():
            now = time.perf_counter()
            if now >= next_toggle:
                velocity = 1.0 if velocity <= 0 else -1.0
                toggles.append((now, velocity))
                next_toggle = now + 0.5
            with lock:
                devices.step(0.005)
                frames = devices.wheel_feedback_frames(
                    {'JLWheel': -sit, 'JRWheel': -sit}, {'JLWheel': velocity, 'JRWheel': velocity}
                )
                frames += devices.imu_frames_from_pitch(sit, 0.0)
            for f in frames:
                buses[f.bus].send(f.msg)
            time.sleep(max(0.0, 0.005 - (time.perf_counter() - now)))

    thread = threading.Thread(target=robot_loop, daemon=True)
    thread.start()
    client, context = open_session_client()
    try:
        deadline = time.monotonic() + 60.0
        while not client.call(
            client.enable,
            SetBool.Request(data=True),
            timeout=max(1.0, deadline - time.monotonic()),
        ).success:
            if time.monotonic() > deadline:
                raise SessionError('adrc_controller did not accept enable')
            client.pause(1.0)
        # whatever message type the wheel command has (it carries the sample's stamp or not)
        client.spin_until(
            lambda: names.WHEEL_EFFORT_CMD in dict(client.get_topic_names_and_types()),
            10.0,
            names.WHEEL_EFFORT_CMD,
        )
        kind = dict(client.get_topic_names_and_types())[names.WHEEL_EFFORT_CMD][0]
        package, _, name = kind.split('/')
        client.create_subscription(
            getattr(importlib.import_module(f'{package}.msg'), name),
            names.WHEEL_EFFORT_CMD,
            lambda m: efforts.append(time.perf_counter()),
            topics.QOS[names.WHEEL_EFFORT_CMD],
        )
        client.pause(seconds)
    finally:
        stop.set()
        client.close()
        rclpy.try_shutdown(context=context)
        nodes.stop()
        for n in notifiers:
            n.stop()
        for bus in buses.values():
            bus.shutdown()
    latencies = []
    cur = np.array(currents)
    for t0, velocity in toggles:
        after = cur[cur[:, 0] > t0] if len(cur) else cur
        before = cur[cur[:, 0] <= t0]
        if not len(after) or not len(before):
            continue
        changed = np.flatnonzero(np.abs(after[:, 1] - before[-1, 1]) > 3.0)
        if changed.size and after[changed[0], 0] - t0 < 0.5:
            latencies.append(after[changed[0], 0] - t0)
    eff = np.array(efforts)
    window = eff[eff > eff[0] + 2.0] if len(eff) else eff
    rate = (len(window) - 1) / (window[-1] - window[0]) if len(window) > 1 else float('nan')
    lat = 1000 * np.array(latencies)
    print(
        f'sensor frame -> wheel command frame over {len(lat)} steps: '
        f'p50 {np.percentile(lat, 50):.1f} ms, p99 {np.percentile(lat, 99):.1f} ms, '
        f'max {lat.max():.1f} ms'
    )
    print(
        f'control rate achieved: {rate:.1f} Hz /wheel_effort_cmd (configured: see '
        f'config/sim_params.yaml); {len(toggles) - len(lat)} of {len(toggles)} steps not seen '
        f'within 0.5 s'
    )
