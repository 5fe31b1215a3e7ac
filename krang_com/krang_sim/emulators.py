"""CAN device emulators for the simulated Krang: each answers as the real device does, frame for
frame.

The emulators are physics-free: they take and give physical quantities (wheel angle, rates,
specific force, module positions) and speak the same wire formats as the robot, through the same
codecs the bridge uses (krang_can_bridge.protocols), so the bridge is exercised against real frame
layouts. ``krang_sim.devices.KrangCanDevices`` holds the robot's set of them, routed by bus.

Design choices (the real behaviour is not knowable from the sources; each is a docstring-level
assumption):
- AMC: a canopen LocalNode provides the SDO server and NMT slave over the drive's object
  dictionary; a DS402 state machine follows the controlword (SDO or RPDO). Current is applied
  only when NMT is OPERATIONAL, the mode is current (4) and the drive is OPERATION_ENABLED - so the
  bridge's start-up sequence is needed, as on the robot (or pass auto_enable=True). TPDOs are
  sent only in OPERATIONAL and when the caller asks: bench/device_player.py at the timer cycle the
  host wrote (`tpdo_period_s`), sim_krang with each of its samples (its feedback_rate_hz), so that
  one lockstep sample is one DMU sample and one TPDO set. Currents beyond the drive peak saturate.
- DMU: adds the configured gyro biases (the bridge removes them), optional white noise (the sensor
  model's figures, krang_sim.sensors), rounds to the DBC's LSB and saturates at int16; streams by
  default (`streaming=False` to exercise the bridge's toggle).
- PowerCube: kinematic module. FRAMP follows a trapezoidal profile within TARGET_VEL /
  TARGET_ACC, themselves capped by the module's datasheet limits; targets are clamped to the
  module soft limits; HALT stops and ignores motions until RESET; FCUR_ACK stores the current and
  holds position (the simulator may `set_state`).
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import can
import canopen
import numpy as np

from krang_can_bridge.config import (
    BodyJointConfig,
    ImuConfig,
    PowerCubeModuleConfig,
    WheelDriveConfig,
    WheelsConfig,
)
from krang_can_bridge.imu_filter import sensor_vectors
from krang_can_bridge.protocols import ProtocolError
from krang_can_bridge.protocols import amc as amc_proto
from krang_can_bridge.protocols import amc_canopen
from krang_can_bridge.protocols import powercube as pc
from krang_can_bridge.protocols.dmu_imu import DmuCodec

INT32_SPAN = 2**32


class _CaptureNetwork(canopen.Network):
    """A canopen Network without a bus: what the local node sends is collected and returned as
    replies."""

    def __init__(self):
        super().__init__(bus=None)
        self.outbox: list[can.Message] = []

    def send_message(self, can_id: int, data, remote: bool = False) -> None:
        self.outbox.append(
            can.Message(
                arbitration_id=can_id,
                data=bytes(data),
                is_extended_id=can_id > 0x7FF,
                is_remote_frame=remote,
            )
        )

    def send_periodic(self, can_id, data, period, remote=False):  # heartbeats: not emulated
        raise NotImplementedError('heartbeat producer is not emulated')

    def take(self) -> list[can.Message]:
        out, self.outbox = self.outbox, []
        return out


class AmcDriveEmulator:
    """One AMC drive: RPDO current in, TPDOs out, NMT and SDO through canopen."""

    def __init__(
        self, drive: WheelDriveConfig, wheels: WheelsConfig, dbc, auto_enable: bool = False
    ):
        self.codec = amc_proto.AmcDriveCodec(drive, wheels, dbc)
        self.drive = drive
        self.wheels = wheels
        self.joint = drive.joint
        self.node = canopen.LocalNode(drive.node_id, amc_canopen.object_dictionary(drive))
        self.node.add_write_callback(self._on_sdo_write)
        self._network = _CaptureNetwork()
        self._network.add_node(self.node)
        self._commanded_dc2_amps = 0.0
        self._last_controlword = 0
        self.malformed = 0
        self._boot()
        self._network.take()  # nobody listens to the power-on boot-up message
        if auto_enable:
            self.node.nmt.send_command(amc_proto.NMT_START)
            self.mode = amc_proto.OP_MODE_CURRENT
            self.state = 'OPERATION_ENABLED'

    def _boot(self) -> None:
        self.state = 'SWITCH_ON_DISABLED'
        self.mode = 0
        self._commanded_dc2_amps = 0.0
        self.node.nmt.send_command(amc_proto.NMT_RESET_NODE)  # boot-up message
        self.node.nmt.send_command(amc_proto.NMT_PRE_OPERATIONAL)

    # ---- state ----------------------------------------------------------------------------------
    @property
    def nmt_state(self) -> str:
        return self.node.nmt.state

    @property
    def statusword(self) -> int:
        return amc_proto.STATUSWORD_OF_STATE.get(self.state, 0)

    @property
    def enabled(self) -> bool:
        return (
            self.nmt_state == 'OPERATIONAL'
            and self.state == 'OPERATION_ENABLED'
            and self.mode == amc_proto.OP_MODE_CURRENT
        )

    @property
    def tpdo_period_s(self) -> float | None:
        """The TPDO timer cycle the host wrote at start-up (timer 1, ms); None while it is 0, the
        power-on value, where the timer sends nothing. The emulator sends TPDOs when its caller
        asks (`tpdo_frames`): a caller that plays the drives in real time asks at this period."""
        ms = self.node.sdo[amc_proto.TIMER1_CYCLE].raw
        return ms / 1000.0 if ms else None

    @property
    def commanded_current_a(self) -> float:
        """Motor current the drive applies, signed in the wheel joint's direction [A]; 0 unless
        enabled."""
        return self._commanded_dc2_amps if self.enabled else 0.0

    @property
    def wheel_torque_nm(self) -> float:
        """Torque at the wheel for the applied current (Kt * gear * I, the drive constants of the
        config)."""
        return self.wheels.current_to_effort(self.commanded_current_a)

    def fault(self) -> None:
        """Inject a drive fault: current drops to zero until a fault reset and re-enable."""
        self.state = 'FAULT'

    def _apply_controlword(self, cw: int) -> None:
        """DS402 state machine. AMC's PDO controlword 0x008F sets bit 7 with 'enable operation':
        bit 7 acts only on its rising edge in FAULT; otherwise the low bits decide (an assumption
        matching the driver)."""
        rising_reset = bool(cw & 0x80) and not (self._last_controlword & 0x80)
        self._last_controlword = cw
        s = self.state
        if s == 'FAULT':
            if rising_reset:
                self.state = 'SWITCH_ON_DISABLED'
            return
        if not cw & 0x02:  # disable voltage
            self.state = 'SWITCH_ON_DISABLED'
        elif not cw & 0x04:  # quick stop
            self.state = 'QUICK_STOP_ACTIVE' if s == 'OPERATION_ENABLED' else 'SWITCH_ON_DISABLED'
        elif not cw & 0x01:  # shutdown
            if s in ('SWITCH_ON_DISABLED', 'SWITCHED_ON', 'OPERATION_ENABLED'):
                self.state = 'READY_TO_SWITCH_ON'
        elif not cw & 0x08:  # switch on / disable operation
            if s in ('READY_TO_SWITCH_ON', 'OPERATION_ENABLED'):
                self.state = 'SWITCHED_ON'
        elif s in ('SWITCHED_ON', 'QUICK_STOP_ACTIVE'):  # enable operation
            self.state = 'OPERATION_ENABLED'

    def _on_sdo_write(self, index, subindex, od, data):
        if index == amc_proto.CONTROLWORD:
            self._apply_controlword(int.from_bytes(data, 'little'))
        elif index == amc_proto.MODES_OF_OPERATION:
            self.mode = int.from_bytes(data, 'little', signed=True)
            self.node.data_store.setdefault(amc_proto.MODES_OF_OPERATION_DISPLAY, {})[0] = bytes(
                data
            )

    # ---- frames ---------------------------------------------------------------------------------
    def on_frame(self, msg: can.Message) -> list[can.Message]:
        """Consume a host frame (NMT, SDO request, RPDO); return the drive's replies."""
        aid = msg.arbitration_id
        if aid == self.codec.ids[amc_proto.RPDO_CURRENT]:
            if self.nmt_state == 'OPERATIONAL':
                try:
                    cw, amps = self.codec.decode_current_command(msg)
                except ProtocolError:
                    self.malformed += 1
                    return []
                self._apply_controlword(cw)
                self._commanded_dc2_amps = amps
            return []
        if aid in (0, 0x600 + self.drive.node_id):
            self._network.notify(aid, bytes(msg.data), msg.timestamp)
            if self.node.nmt.state == 'INITIALISING':  # NMT reset: reboot
                self._boot()
            return self._network.take()
        return []

    def tpdo_frames(
        self, position_rad: float, velocity_rad_s: float, current_a: float | None = None
    ) -> list[can.Message]:
        """TPDO position, velocity, current and statusword for the wheel state (none unless
        OPERATIONAL).

        `current_a` defaults to the applied current (an ideal current loop); the position counter
        wraps at 32 bits like the drive's.
        """
        if self.nmt_state != 'OPERATIONAL':
            return []
        sw = self.statusword
        counts = self.codec.position_counts(position_rad)
        counts = (counts + 2**31) % INT32_SPAN - 2**31
        cur = self.commanded_current_a if current_a is None else current_a
        cur = max(-self.drive.peak_current_a, min(self.drive.peak_current_a, cur))
        return [
            self.codec.encode_position_counts(counts, sw),
            self.codec.encode_velocity(velocity_rad_s, sw),
            self.codec.encode_actual_current(cur, sw),
            self.codec.encode_statusword(sw),
        ]


class DmuImuEmulator:
    """The DMU: 0x40/0x50 frames from sensor-frame rates and specific force, 0x90 toggles
    streaming."""

    def __init__(
        self,
        imu: ImuConfig,
        dbc,
        streaming: bool = True,
        rate_noise_std_rad_s: float = 0.0,
        accel_noise_std_m_s2: float = 0.0,
        add_bias: bool = True,
        seed: int | None = None,
    ):
        self.config = imu
        self.codec = DmuCodec(dbc)
        self.streaming = streaming
        self.rate_noise_std = rate_noise_std_rad_s
        self.accel_noise_std = accel_noise_std_m_s2
        self.bias = np.array(imu.gyro_bias_rad_s if add_bias else (0.0, 0.0, 0.0))
        self.rng = np.random.default_rng(seed)
        self.sequence = 0
        self.status = 0

    def on_frame(self, msg: can.Message) -> list[can.Message]:
        try:
            if self.codec.is_stream_toggle(msg):
                self.streaming = not self.streaming
        except ProtocolError:
            pass
        return []

    def _raw(self, values: np.ndarray, lsb: float) -> list[int]:
        return [int(min(2**15 - 1, max(-(2**15), round(v / lsb)))) for v in values]

    def frames(
        self, rates_rad_s: Sequence[float], specific_force_m_s2: Sequence[float]
    ) -> list[can.Message]:
        """One sample (rates frame + accelerations frame, same sequence number), in sensor axes."""
        if not self.streaming:
            return []
        w = np.asarray(rates_rad_s, dtype=float) + self.bias
        f = np.asarray(specific_force_m_s2, dtype=float)
        if self.rate_noise_std:
            w = w + self.rng.normal(0.0, self.rate_noise_std, 3)
        if self.accel_noise_std:
            f = f + self.rng.normal(0.0, self.accel_noise_std, 3)
        if not (np.all(np.isfinite(w)) and np.all(np.isfinite(f))):
            raise ValueError('DMU emulator given non-finite rates or specific force')
        seq = self.sequence
        self.sequence = (self.sequence + 1) & 0xFF
        return [
            self.codec.encode_raw_rates(self._raw(w, self.codec.rate_lsb_rad_s), self.status, seq),
            self.codec.encode_raw_accelerations(
                self._raw(f, self.codec.accel_lsb_m_s2), self.status, seq
            ),
        ]

    def frames_from_pitch(
        self,
        pitch: float,
        pitch_rate: float,
        gravity: float = 9.81,
        forward_specific_force: float = 0.0,
        up_specific_force: float | None = None,
    ) -> list[can.Message]:
        """A sample for a robot at base pitch `pitch` (hardware convention) turning at
        `pitch_rate`, honouring the mount angle; specific force in the pitch plane as in
        krang_can_bridge.imu_filter.sensor_vectors."""
        force, rates = sensor_vectors(
            pitch,
            pitch_rate,
            self.config.mount_angle_rad,
            gravity,
            forward_specific_force,
            up_specific_force,
        )
        return self.frames(rates, force)


class PowerCubeEmulator:
    """One kinematic PowerCube module in module coordinates [rad, rad/s].

    ``position`` and ``velocity`` are the module's motion profile, which its servo follows. What
    it reports as its position (``ACT_FPOS`` and the motion replies) is its encoder: the profile
    itself, or, when a simulator with joint dynamics sets ``encoder`` (a callable), that joint's
    angle, which trails the profile under load as a real module's does."""

    def __init__(
        self,
        module_id: int,
        max_velocity: float,
        max_acceleration: float,
        min_position: float,
        max_position: float,
        position: float = 0.0,
        homed: bool = True,
    ):
        self.module_id = module_id
        self.max_velocity = max_velocity
        self.max_acceleration = max_acceleration
        self.min_position = min_position
        self.max_position = max_position
        self.target_velocity = max_velocity
        self.target_acceleration = max_acceleration
        self.position = min(max_position, max(min_position, position))
        self.velocity = 0.0
        self.target = self.position
        self.mode = 'ramp'  # 'ramp' | 'velocity' | 'current'
        self.commanded_velocity = 0.0
        self.commanded_current = 0.0
        self.homed = homed
        self.halted = False
        self.error = False
        self.params: dict[int, float | int] = {}
        self.malformed = 0
        self.encoder: Callable[[], float] | None = None

    @property
    def measured_position(self) -> float:
        """What the module's encoder reads: the joint if a simulator gives it, else the
        profile."""
        return self.position if self.encoder is None else self.encoder()

    @classmethod
    def from_config(cls, joint: BodyJointConfig, module: PowerCubeModuleConfig, q: float = 0.0):
        lower, upper = joint.module_limits(module)
        return cls(
            module.module_id,
            joint.max_velocity_rad_s,
            joint.max_acceleration_rad_s2,
            lower,
            upper,
            position=module.sign * joint.clamp(q),
        )

    # ---- state words ----------------------------------------------------------------------------
    @property
    def in_motion(self) -> bool:
        return abs(self.velocity) > 1e-9 or (
            self.mode == 'ramp' and abs(self.target - self.position) > 1e-9
        )

    def long_state(self) -> int:
        s = (pc.STATE_HOME_OK if self.homed else 0) | (pc.STATE_HALTED if self.halted else 0)
        s |= pc.STATE_ERROR if self.error else 0
        s |= (
            pc.STATE_MOTION
            if self.in_motion
            else (pc.STATE_RAMP_END if self.mode == 'ramp' else 0)
        )
        return s

    def short_state(self) -> int:
        s = pc.SHORT_NOT_OK if (self.error or not self.homed or self.halted) else 0
        s |= (
            pc.SHORT_MOTION
            if self.in_motion
            else (pc.SHORT_RAMP_END if self.mode == 'ramp' else 0)
        )
        return s

    def set_state(self, position: float, velocity: float = 0.0) -> None:
        """Override the kinematics (e.g. a simulator driving a current-mode module)."""
        self.position, self.velocity = position, velocity

    # ---- protocol -------------------------------------------------------------------------------
    def _param_value(self, param: int) -> float | int | None:
        if param == pc.ACT_FPOS:
            return self.measured_position  # (read only when asked: a simulator's joint)
        values = {
            pc.ACT_FVEL: self.velocity,
            pc.MIN_FPOS: self.min_position,
            pc.MAX_FPOS: self.max_position,
            pc.MAX_VEL: self.max_velocity,
            pc.MAX_ACC: self.max_acceleration,
            pc.TARGET_VEL: self.target_velocity,
            pc.TARGET_ACC: self.target_acceleration,
            pc.ACT_FPSEUDOCURRENT: self.commanded_current,
            pc.CUBE_STATE: self.long_state(),
        }
        return values.get(param, self.params.get(param))

    def on_frame(self, msg: can.Message) -> list[can.Message]:
        """Consume a host frame; reply as the module does (frames for other modules are
        ignored)."""
        try:
            req = pc.decode_request(msg)
        except pc.UnknownFrame:
            return []
        except ProtocolError:
            if msg.arbitration_id & pc.MODULE_ID_MASK == self.module_id:
                self.malformed += 1
            return []
        if req.module_id is not None and req.module_id != self.module_id:
            return []
        broadcast = req.module_id is None
        mid = self.module_id
        if req.command in pc.SIMPLE_COMMANDS:
            if req.command == pc.RESET:
                self.halted = self.error = False
                self.target, self.velocity, self.mode = self.position, 0.0, 'ramp'
            elif req.command == pc.HALT:
                self.halted = True
                self.velocity, self.target, self.mode = 0.0, self.position, 'ramp'
            elif req.command == pc.HOME:
                self.homed = True
            return [] if broadcast else [pc.reply_simple(mid, req.command)]
        if broadcast:
            return []
        if req.command == pc.GET_PARAM:
            value = self._param_value(req.selector)
            return [] if value is None else [pc.reply_get_param(mid, req.selector, value)]
        if req.command == pc.SET_PARAM:
            v = req.value
            if req.selector == pc.TARGET_VEL:
                self.target_velocity = min(abs(float(v)), self.max_velocity)
            elif req.selector == pc.TARGET_ACC:
                self.target_acceleration = min(abs(float(v)), self.max_acceleration)
            elif req.selector == pc.MIN_FPOS:
                self.min_position = float(v)
            elif req.selector == pc.MAX_FPOS:
                self.max_position = float(v)
            else:
                self.params[req.selector] = v
            return [pc.reply_set_param(mid, req.selector)]
        # SET_MOTION
        if not (self.halted or self.error):
            if req.selector == pc.FRAMP_ACK:
                self.mode, self.target = (
                    'ramp',
                    min(self.max_position, max(self.min_position, req.value)),
                )
            elif req.selector == pc.FVEL_ACK:
                self.mode = 'velocity'
                self.commanded_velocity = max(
                    -self.max_velocity, min(self.max_velocity, req.value)
                )
            else:
                self.mode, self.commanded_current, self.velocity = 'current', req.value, 0.0
        return [pc.reply_motion(mid, req.selector, self.measured_position, self.short_state())]

    def step(self, dt: float) -> bool:
        """Advance the module by dt seconds within its velocity and acceleration limits; whether
        its position changed."""
        if dt <= 0.0 or self.halted or self.mode == 'current':
            return False
        if (
            self.mode == 'ramp'
            and self.velocity == 0.0
            and self.position == self.target
            and self.min_position <= self.position <= self.max_position
        ):
            return False  # at rest on its target: the step below changes nothing (1 kHz x 17)
        a = self.target_acceleration
        if self.mode == 'ramp':
            # Discrete braking curve: from v = (k + f) a dt, braking by a dt per step covers
            # a dt^2 (k + 1)(k/2 + f) and lands exactly on the target; take the largest such v.
            err = self.target - self.position
            x = abs(err) / (a * dt * dt)
            k = math.floor((math.sqrt(1.0 + 8.0 * x) - 1.0) / 2.0)
            f = min(1.0, max(0.0, x / (k + 1) - k / 2.0))
            v_des = math.copysign(min(self.target_velocity, (k + f) * a * dt), err)
        else:
            v_des = self.commanded_velocity
        self.velocity += max(-a * dt, min(a * dt, v_des - self.velocity))
        new_position = self.position + self.velocity * dt
        if (
            self.mode == 'ramp'
            and (self.target - new_position) * (self.target - self.position) <= 0.0
        ):
            new_position = self.target  # arrived; the braking curve ends at 0
            if abs(self.velocity) > a * dt:  # only a target change can cause this
                self.velocity = 0.0
        if not self.min_position <= new_position <= self.max_position:
            new_position = min(self.max_position, max(self.min_position, new_position))
            self.velocity = 0.0
        moved, self.position = new_position != self.position, new_position
        return moved
