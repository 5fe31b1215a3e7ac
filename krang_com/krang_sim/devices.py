"""Krang's CAN devices for the simulator: every emulator of the device map (krang_sim.emulators),
routed by bus, as one object the simulator (krang_sim/node.py) drives::

    devices = KrangCanDevices(load_devices())  # every emulator from config/can_devices.yaml
    replies = devices.on_frame(bus, msg)  # host frame in -> device replies out (BusFrames)
    devices.step(dt)  # PowerCube ramps advance
    amps = devices.wheels['JLWheel'].commanded_current_a  # -> physics
    devices.set_silent(['imu'])  # fault injection: the DMU stops transmitting
    out = devices.wheel_feedback_frames({'JLWheel': q, ...}, {'JLWheel': dq, ...})  # -> bus
    out += devices.imu_frames_from_pitch(q_base, dq_base)  # -> bus

A silent device (fault injection, `set_silent`) stops transmitting (a broken TX line or a hung
firmware loop) but still receives, so a drive applies the zero current a bridge sends once it
notices the silence.
"""

from __future__ import annotations

import functools
from typing import Callable, Mapping, Sequence

import can

from krang_can_bridge.config import CanDevicesConfig, PowerCubeModuleConfig
from krang_can_bridge.protocols import load_dbc
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols import powercube as pc
from krang_can_bridge.snapshots import BusFrame

from .emulators import AmcDriveEmulator, DmuImuEmulator, PowerCubeEmulator


class KrangCanDevices:
    """All of Krang's CAN devices from the device map, routed by bus: one object for the simulator
    to drive."""

    def __init__(
        self,
        config: CanDevicesConfig,
        auto_enable_wheels: bool = False,
        imu_streaming: bool = True,
        imu_rate_noise_std_rad_s: float = 0.0,
        imu_accel_noise_std_m_s2: float = 0.0,
        seed: int | None = None,
        initial_joint_positions: Mapping[str, float] | None = None,
    ):
        self.config = config
        dbc = load_dbc(config.dbc_path)
        self.wheels = {
            d.joint: AmcDriveEmulator(d, config.wheels, dbc, auto_enable_wheels)
            for d in config.wheels.drives
        }
        self.imu = DmuImuEmulator(
            config.imu,
            dbc,
            imu_streaming,
            imu_rate_noise_std_rad_s,
            imu_accel_noise_std_m_s2,
            seed=seed,
        )
        q0 = dict(initial_joint_positions or {})
        self.modules: dict[tuple[str, int], PowerCubeEmulator] = {}
        self.joint_modules: dict[str, list[tuple[PowerCubeModuleConfig, PowerCubeEmulator]]] = {}
        for joint in config.powercube.joints:
            q = joint.clamp(q0.get(joint.joint, joint.clamp(0.0)))
            for m in joint.modules:
                em = PowerCubeEmulator.from_config(joint, m, q)
                self.modules[(m.bus, m.module_id)] = em
                self.joint_modules.setdefault(joint.joint, []).append((m, em))
        self.module_joint = {
            (m.bus, m.module_id): j for j, mods in self.joint_modules.items() for m, _ in mods
        }
        self._bus_modules: dict[str, list[tuple[int, PowerCubeEmulator]]] = {}
        for (b, mid), em in self.modules.items():
            self._bus_modules.setdefault(b, []).append((mid, em))
        self.silent: frozenset[str] = frozenset()

    @property
    def device_names(self) -> list[str]:
        """What `set_silent` accepts: 'imu', the wheel joints (their drives) and the body joints
        (their modules)."""
        return ['imu', *self.wheels, *self.joint_modules]

    def set_silent(self, names: Sequence[str]) -> None:
        """Silence these devices (see the module docstring); an empty list restores them all."""
        unknown = sorted(set(names) - set(self.device_names))
        if unknown:
            raise ValueError(f'unknown device(s) {unknown}; known: {self.device_names}')
        self.silent = frozenset(names)

    def on_frame(self, bus: str, msg: can.Message) -> list[BusFrame]:
        """Deliver a host frame to the devices on `bus`; their replies, tagged with the bus."""
        out: list[can.Message] = []
        if bus == self.config.wheels.bus:
            for joint, w in self.wheels.items():
                out += self._unless_silent(joint, w.on_frame(msg))
        if bus == self.config.imu.bus:
            out += self._unless_silent('imu', self.imu.on_frame(msg))
        aid = msg.arbitration_id
        if pc.is_host_frame(aid):
            # a module ignores frames addressed to another one: only the addressee (or, for a
            # broadcast, every module of the bus) sees it
            target = None if aid == pc.BROADCAST_ID else aid & pc.MODULE_ID_MASK
            for mid, em in self._bus_modules.get(bus, ()):
                if target is None or mid == target:
                    out += self._unless_silent(self.module_joint[(bus, mid)], em.on_frame(msg))
        return [BusFrame(bus, m) for m in out]

    def host_ids(self, bus: str) -> set[int]:
        """The ids of the host frames the devices on `bus` read: a process playing them needs
        no other frame (bus_io.receive_only)."""
        ids = set()
        if bus == self.config.wheels.bus:
            for w in self.wheels.values():
                ids |= {w.codec.ids[amc_proto.RPDO_CURRENT], 0x000, 0x600 + w.drive.node_id}
        if bus == self.config.imu.bus:
            ids |= self.imu.codec.command_ids
        for mid, _ in self._bus_modules.get(bus, ()):
            ids |= {pc.GET_BASE + mid, pc.PUT_BASE + mid, pc.BROADCAST_ID}
        return ids

    def _unless_silent(self, device: str, frames: list) -> list:
        return [] if device in self.silent else frames

    def step(self, dt: float) -> bool:
        """Advance every module by dt seconds; whether any joint position changed (a simulator
        need not read them otherwise)."""
        moved = False
        for em in self.modules.values():
            moved = em.step(dt) or moved
        return moved

    def joint_positions(self) -> dict[str, float]:
        """Body joint angles [rad] as the modules hold them (waist: mean of sign * module
        position)."""
        return {
            j: sum(m.sign * em.position for m, em in mods) / len(mods)
            for j, mods in self.joint_modules.items()
        }

    def read_joints_from(self, joints: Callable[[], Mapping[str, float]] | None) -> None:
        """The modules' encoders read the joint angles `joints()` gives (rad, by joint; a
        simulator's plant through its sensor model), asked at each poll; None: each module
        reports its own motion profile. A module's servo trails its profile under load, and the
        encoder reads the joint, not the profile."""
        for joint, mods in self.joint_modules.items():
            for m, em in mods:
                em.encoder = (
                    None
                    if joints is None
                    else functools.partial(_module_angle, joints, joint, m.sign)
                )

    def joint_velocities(self) -> dict[str, float]:
        return {
            j: sum(m.sign * em.velocity for m, em in mods) / len(mods)
            for j, mods in self.joint_modules.items()
        }

    def wheel_currents(self) -> dict[str, float]:
        return {j: w.commanded_current_a for j, w in self.wheels.items()}

    def wheel_feedback_frames(
        self,
        positions_rad: Mapping[str, float],
        velocities_rad_s: Mapping[str, float],
        currents_a: Mapping[str, float] | None = None,
    ) -> list[BusFrame]:
        out = []
        for j, w in self.wheels.items():
            cur = None if currents_a is None else currents_a.get(j)
            out += [
                BusFrame(self.config.wheels.bus, m)
                for m in self._unless_silent(
                    j, w.tpdo_frames(positions_rad[j], velocities_rad_s[j], cur)
                )
            ]
        return out

    def sensor_frames(self, motion, sensors) -> list[BusFrame]:
        """One sample's frames: the plant's `motion` (``krang_sim.plant.Motion``) as the devices
        report it through the sensor model `sensors` (``krang_sim.sensors.SensorModel``): every
        drive's TPDOs and the DMU's rates and accelerations."""
        (left, right), (left_rate, right_rate) = sensors.encoders(motion)
        frames = self.wheel_feedback_frames(
            {'JLWheel': left, 'JRWheel': right}, {'JLWheel': left_rate, 'JRWheel': right_rate}
        )
        pitch, pitch_rate, forward, up = sensors.dmu_inputs(motion)
        return frames + self.imu_frames_from_pitch(
            pitch, pitch_rate, forward_specific_force=forward, up_specific_force=up
        )

    # a silent DMU keeps sampling (its sequence counter runs on), it only stops transmitting
    def imu_frames(
        self, rates_rad_s: Sequence[float], specific_force_m_s2: Sequence[float]
    ) -> list[BusFrame]:
        frames = self.imu.frames(rates_rad_s, specific_force_m_s2)
        return [BusFrame(self.config.imu.bus, m) for m in self._unless_silent('imu', frames)]

    def imu_frames_from_pitch(self, pitch: float, pitch_rate: float, **kwargs) -> list[BusFrame]:
        frames = self.imu.frames_from_pitch(pitch, pitch_rate, **kwargs)
        return [BusFrame(self.config.imu.bus, m) for m in self._unless_silent('imu', frames)]


def _module_angle(joints, joint: str, sign: float) -> float:
    return sign * joints()[joint]
