"""Typed view of config/can_devices.yaml: buses, devices, device constants and command limits.

Everything the bridge, the codecs and the emulators need to know about the robot's CAN side comes
from here: what is specific to the devices from the YAML (or the DBC for the IMU's LSB scales), the
drive train (torque constant, gear ratio, current limit) from krang_model.drivetrain, the one
description every user of a motor constant reads. A device map may still state a drive-train value
(`wheels.torque_constant_nm_per_a`, `gear_ratio`, `current_limit_a`); it is then checked against
the drive train at load. The loader validates the file so that a typo or a disagreeing constant
fails at start-up, not as a wrong current on the bus. docs/can.md describes the devices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import yaml

from krang_model.config import config_path
from krang_model.drivetrain import Drivetrain, drivetrain
from krang_model.robot import load_krang

DEVICES_FILE_NAME = 'can_devices.yaml'  # the simulated robot (udp_multicast)
ROBOT_DEVICES_FILE_NAME = 'can_devices_robot.yaml'  # the robot (SocketCAN): bridge default
WATCHDOG_MECHANISMS = ('heartbeat', 'guarding', 'none')
CAN_BITRATE = 1_000_000  # every Krang net runs at 1 Mbit/s (docs/can.md)


class ConfigError(ValueError):
    """The device map is inconsistent or incomplete."""


@dataclass(frozen=True)
class BusConfig:
    """One CAN bus: python-can `interface` and `channel`, plus any extra `can.Bus` keyword
    arguments."""

    name: str
    interface: str
    channel: str
    options: Mapping[str, Any] = field(default_factory=dict)

    def bus_kwargs(self) -> dict:
        """Keyword arguments for `can.Bus(**kwargs)`."""
        return {'interface': self.interface, 'channel': self.channel, **dict(self.options)}


@dataclass(frozen=True)
class WheelDriveConfig:
    """One AMC drive. `sign` flips current, position and velocity (amciod: right drive -1)."""

    joint: str
    node_id: int
    sign: int
    peak_current_kp: float  # drive object 0x20D8.0C, units of 0.1 A
    k_i: float  # feedback interpolation, 0x2032.08
    k_s: float  # switching frequency in Hz (0x20D8.24)

    @property
    def peak_current_a(self) -> float:
        return self.peak_current_kp / 10.0


@dataclass(frozen=True)
class WatchdogConfig:
    """What stops the drives by themselves when the bridge dies or hangs (docs/can.md, "Drive-side
    watchdog").

    heartbeat: the bridge produces heartbeats (0x700 + node_id) every period_s; each drive
    consumes them (0x1016) and takes `abort_connection_option` (0x6007) when none came for
    timeout_s. guarding: the bridge sends node-guarding requests every period_s (guard time 0x100C)
    and a drive that hears none for timeout_s (guard time x life time factor 0x100D) takes 0x6007.
    The bridge beats only while its command loop ran within alive_timeout_s.
    """

    mechanism: str
    node_id: int
    period_s: float
    timeout_s: float
    alive_timeout_s: float
    abort_connection_option: int

    @property
    def period_ms(self) -> int:
        return round(self.period_s * 1000.0)

    @property
    def timeout_ms(self) -> int:
        return round(self.timeout_s * 1000.0)

    @property
    def life_time_factor(self) -> int:
        return round(self.timeout_s / self.period_s)


@dataclass(frozen=True)
class WheelsConfig:
    """The AMC drives; `drivetrain` is the robot's (krang_model.drivetrain), not the YAML's."""

    bus: str
    encoder_counts_per_rev: float  # motor encoder, read by the drive
    tpdo_period_ms: int  # the drives' TPDO timer (AMC timer 1), written at start-up
    silence_timeout_s: float
    command_timeout_s: float
    command_rate_hz: float
    required: bool
    drives: tuple[WheelDriveConfig, ...]
    drivetrain: Drivetrain
    watchdog: WatchdogConfig

    @property
    def counts_per_wheel_rad(self) -> float:
        return self.encoder_counts_per_rev * self.drivetrain.gear_ratio / (2.0 * math.pi)

    def effort_to_current(self, effort_nm: float) -> float:
        """Motor current for a torque at the wheel: tau = Kt * gear * I (no clamping)."""
        return effort_nm / (self.drivetrain.torque_constant * self.drivetrain.gear_ratio)

    def current_to_effort(self, current_a: float) -> float:
        """Torque at the wheel for a motor current (the inverse of effort_to_current)."""
        return current_a * self.drivetrain.torque_constant * self.drivetrain.gear_ratio

    def drive(self, joint: str) -> WheelDriveConfig:
        for d in self.drives:
            if d.joint == joint:
                return d
        raise KeyError(joint)


@dataclass(frozen=True)
class KalmanConfig:
    process_k1: float
    process_k1b: float
    measurement_noise_angle: float  # accelerometer pitch (corrupted by linear acceleration)
    measurement_noise_rate: float  # gyro pitch rate
    init_samples: int
    # gyro-bias random walk [(rad/s)^2/s]: how fast the bias is tracked
    bias_process_noise: float
    # start-up: still = the accelerometer pitch turns slower than this,
    still_rate_rad_s: float
    still_rate_change_rad_s: float  # and the gyro mean changes less than this across the window;
    still_wait_s: float  # no still window within this long: start without the bias


@dataclass(frozen=True)
class ImuConfig:
    bus: str
    mount_angle_rad: float
    gyro_bias_rad_s: tuple[float, float, float]  # about sensor x (dQ), y (dP), z (dR)
    silence_timeout_s: float
    stream_toggle_retry_s: float
    required: bool
    frame_id: str
    kalman: KalmanConfig
    # A DMU whose six values stay bit-identical this long is frozen (its noise changes them at
    # every sample); 0: not checked (a noise-free simulated DMU repeats its values at rest)
    frozen_after_s: float = 0.0


@dataclass(frozen=True)
class PowerCubeModuleConfig:
    """One module; its position is `sign * q` for the joint q it drives."""

    bus: str
    module_id: int
    sign: int


@dataclass(frozen=True)
class BodyJointConfig:
    joint: str
    lower: float
    upper: float
    module_type: str
    max_velocity_rad_s: float
    max_acceleration_rad_s2: float
    modules: tuple[PowerCubeModuleConfig, ...]

    def clamp(self, q: float) -> float:
        return min(self.upper, max(self.lower, q))

    def module_limits(self, module: PowerCubeModuleConfig) -> tuple[float, float]:
        """Joint limits in module coordinates (sign-inverted for a sign -1 module)."""
        a, b = module.sign * self.lower, module.sign * self.upper
        return (min(a, b), max(a, b))


@dataclass(frozen=True)
class PowerCubeConfig:
    poll_rate_hz: float
    silence_timeout_s: float
    required: bool
    joints: tuple[BodyJointConfig, ...]

    def joint(self, name: str) -> BodyJointConfig:
        for j in self.joints:
            if j.joint == name:
                return j
        raise KeyError(name)


@dataclass(frozen=True)
class CanDevicesConfig:
    path: Path
    dbc_path: Path
    buses: Mapping[str, BusConfig]
    wheels: WheelsConfig
    imu: ImuConfig
    powercube: PowerCubeConfig

    @property
    def body_joint_names(self) -> list[str]:
        return [j.joint for j in self.powercube.joints]

    @property
    def wheel_joint_names(self) -> list[str]:
        return [d.joint for d in self.wheels.drives]

    @property
    def joint_names(self) -> list[str]:
        """Names published on /joint_states: body joints, then the wheels (URDF names)."""
        return self.body_joint_names + self.wheel_joint_names

    def buses_in_use(self) -> list[str]:
        """Buses that carry at least one bridged device, in config order."""
        used = {self.wheels.bus, self.imu.bus}
        used |= {m.bus for j in self.powercube.joints for m in j.modules}
        return [name for name in self.buses if name in used]

    def bus_for_channel(self, channel: Any) -> str | None:
        """Bus name whose configured channel equals `channel` (for frames that carry only
        msg.channel)."""
        for name, bus in self.buses.items():
            if str(bus.channel) == str(channel) or name == channel:
                return name
        return None


def default_devices_file() -> Path:
    """The simulated robot's map, config/can_devices.yaml of the config directory robot.yaml comes
    from (the source tree's, else the installed share/krang_com/config), so the map and the drive
    train always match."""
    return config_path(DEVICES_FILE_NAME)


def robot_devices_file() -> Path:
    """The robot's SocketCAN map (config/can_devices_robot.yaml): what can_bridge uses unless told
    otherwise."""
    return config_path(ROBOT_DEVICES_FILE_NAME)


def resolve_devices_file(name: str | Path) -> Path:
    """A `devices_file` value: a bare file name is looked up in config/, anything else is a
    path."""
    path = Path(name)
    return config_path(str(path)) if len(path.parts) == 1 and not path.exists() else path


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> tuple[dict, dict]:
    """Read a device map; `extends: other.yaml` inherits every top-level key the file does not set.
    Returns (data, {top-level key: the file it came from})."""
    path = path.resolve()
    if path in seen:
        raise ConfigError(f'circular extends: {path}')
    try:
        with open(path) as f:
            data = yaml.safe_load(f) or {}
    except (OSError, yaml.YAMLError) as exc:
        reason = ' '.join(str(exc).split())  # YAML's messages span lines
        raise ConfigError(f'cannot read {path}: {reason}') from exc
    if not isinstance(data, dict):
        raise ConfigError(f'{path}: top level must be a mapping')
    parent = data.pop('extends', None)
    sources = {key: path for key in data}
    if parent is None:
        return data, sources
    merged, merged_sources = _read_yaml(path.parent / parent, seen + (path,))
    merged.update(data)
    merged_sources.update(sources)
    return merged, merged_sources


def _req(d: Mapping, key: str, where: str) -> Any:
    if not isinstance(d, Mapping) or key not in d:
        raise ConfigError(f'{where}: missing key {key!r}')
    return d[key]


def _positive(value: Any, where: str) -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0.0:
        raise ConfigError(f'{where} must be a positive finite number, got {value!r}')
    return v


def _non_negative(value: Any, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if not math.isfinite(v) or v < 0.0:
        raise ConfigError(f'{where} must be a finite number >= 0, got {value!r}')
    return v


def _sign(value: Any, where: str) -> int:
    if value not in (1, -1):
        raise ConfigError(f'{where}: sign must be 1 or -1, got {value!r}')
    return int(value)


# Drive-train values a device map may still state, and the Drivetrain field each must equal.
DRIVETRAIN_KEYS = {
    'torque_constant_nm_per_a': 'torque_constant',
    'gear_ratio': 'gear_ratio',
    'current_limit_a': 'current_limit',
}


def _check_drivetrain(d: Mapping, drive: Drivetrain, source: Path) -> None:
    """A drive-train value in the device map must be the drive train's (config/robot.yaml)."""
    for key, attr in DRIVETRAIN_KEYS.items():
        if key not in d:
            continue
        stated, expected = float(d[key]), float(getattr(drive, attr))
        if not math.isclose(stated, expected, rel_tol=1e-12, abs_tol=0.0):
            raise ConfigError(
                f'{source}: wheels.{key} = {d[key]!r} disagrees with the drive train ({attr} = '
                f'{expected!r}, config/robot.yaml via krang_model.drivetrain); remove the key '
                'from the device map or make the two agree'
            )


def _parse_watchdog(
    d: Any, drives: list[WheelDriveConfig], command_rate_hz: float
) -> WatchdogConfig:
    """wheels.watchdog, checked so that a drive can never trip on a healthy bridge nor wait
    forever on a dead one."""
    where = 'wheels.watchdog'
    if not isinstance(d, Mapping):
        raise ConfigError(f'{where}: missing (a mapping: mechanism, node_id, period_s, ...)')
    mechanism = str(_req(d, 'mechanism', where))
    if mechanism not in WATCHDOG_MECHANISMS:
        raise ConfigError(
            f'{where}.mechanism must be one of {WATCHDOG_MECHANISMS}, got {mechanism!r}'
        )
    node_id = int(_req(d, 'node_id', where))
    if not 1 <= node_id <= 0x7F or node_id in {x.node_id for x in drives}:
        raise ConfigError(f"{where}.node_id {node_id} must be in 1..127 and not a drive's")
    cfg = WatchdogConfig(
        mechanism=mechanism,
        node_id=node_id,
        period_s=_positive(_req(d, 'period_s', where), f'{where}.period_s'),
        timeout_s=_positive(_req(d, 'timeout_s', where), f'{where}.timeout_s'),
        alive_timeout_s=_positive(_req(d, 'alive_timeout_s', where), f'{where}.alive_timeout_s'),
        abort_connection_option=int(_req(d, 'abort_connection_option', where)),
    )
    if not -0x8000 <= cfg.abort_connection_option <= 3:
        raise ConfigError(
            f'{where}.abort_connection_option (0x6007) must be 0..3 (DS402) or a '
            f'negative manufacturer code, got {cfg.abort_connection_option}'
        )
    if cfg.period_s * 3 > cfg.timeout_s:
        raise ConfigError(
            f'{where}: period_s {cfg.period_s} must be at most a third of timeout_s '
            f'{cfg.timeout_s} (a late beat must not trip the drives)'
        )
    if not (1 <= cfg.period_ms and cfg.timeout_ms <= 0xFFFF):
        raise ConfigError(f'{where}: period_s and timeout_s must be 1 ms .. 65.535 s')
    if mechanism == 'guarding' and not 1 <= cfg.life_time_factor <= 0xFF:
        raise ConfigError(f'{where}: timeout_s / period_s (life time factor) must be 1..255')
    if cfg.alive_timeout_s * command_rate_hz < 2:
        raise ConfigError(
            f'{where}.alive_timeout_s {cfg.alive_timeout_s} must span at least two '
            f'wheel command periods (1/{command_rate_hz} s)'
        )
    return cfg


# A drive is declared silent only after this many TPDO periods without a frame, so that one lost or
# late set never stops the robot.
SILENCE_PERIODS_MIN = 3


def _tpdo_period_ms(value: Any, silence_timeout_s: float) -> int:
    """wheels.tpdo_period_ms: a whole number of milliseconds (the AMC timer's unit), short enough
    that `silence_timeout_s` spans SILENCE_PERIODS_MIN periods."""
    where = 'wheels.tpdo_period_ms'
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f'{where} must be a whole number of milliseconds >= 1, got {value!r}')
    if SILENCE_PERIODS_MIN * value > silence_timeout_s * 1000.0:
        raise ConfigError(
            f'{where} = {value} ms: wheels.silence_timeout_s ({silence_timeout_s} s) must span at '
            f'least {SILENCE_PERIODS_MIN} TPDO periods'
        )
    return value


def _parse_wheels(d: Mapping, buses: Mapping, drive: Drivetrain, source: Path) -> WheelsConfig:
    where = 'wheels'
    _check_drivetrain(d, drive, source)
    drives = []
    for i, dd in enumerate(_req(d, 'drives', where)):
        w = f'{where}.drives[{i}]'
        node_id = int(_req(dd, 'node_id', w))
        if not 1 <= node_id <= 0x7F:
            raise ConfigError(f'{w}: CANopen node id {node_id} outside 1..127')
        drives.append(
            WheelDriveConfig(
                joint=str(_req(dd, 'joint', w)),
                node_id=node_id,
                sign=_sign(_req(dd, 'sign', w), w),
                peak_current_kp=_positive(_req(dd, 'peak_current_kp', w), f'{w}.peak_current_kp'),
                k_i=_positive(_req(dd, 'k_i', w), f'{w}.k_i'),
                k_s=_positive(_req(dd, 'k_s', w), f'{w}.k_s'),
            )
        )
    if len({x.node_id for x in drives}) != len(drives) or len({x.joint for x in drives}) != len(
        drives
    ):
        raise ConfigError(f'{where}: duplicate node id or joint')
    silence_timeout_s = _positive(_req(d, 'silence_timeout_s', where), 'wheels.silence_timeout_s')
    cfg = WheelsConfig(
        bus=str(_req(d, 'bus', where)),
        encoder_counts_per_rev=_positive(
            _req(d, 'encoder_counts_per_rev', where), 'encoder_counts_per_rev'
        ),
        tpdo_period_ms=_tpdo_period_ms(_req(d, 'tpdo_period_ms', where), silence_timeout_s),
        silence_timeout_s=silence_timeout_s,
        command_timeout_s=_positive(
            _req(d, 'command_timeout_s', where), 'wheels.command_timeout_s'
        ),
        command_rate_hz=_positive(_req(d, 'command_rate_hz', where), 'wheels.command_rate_hz'),
        required=bool(d.get('required', True)),
        drives=tuple(drives),
        drivetrain=drive,
        watchdog=_parse_watchdog(
            d.get('watchdog'),
            drives,
            _positive(_req(d, 'command_rate_hz', where), 'command_rate_hz'),
        ),
    )
    if cfg.bus not in buses:
        raise ConfigError(f'{where}: unknown bus {cfg.bus!r}')
    return cfg


def _parse_imu(d: Mapping, buses: Mapping) -> ImuConfig:
    where = 'imu'
    bias = _req(d, 'gyro_bias_rad_s', where)
    k = _req(d, 'kalman', where)
    cfg = ImuConfig(
        bus=str(_req(d, 'bus', where)),
        mount_angle_rad=float(_req(d, 'mount_angle_rad', where)),
        gyro_bias_rad_s=(
            float(_req(bias, 'x', 'imu.gyro_bias_rad_s')),
            float(_req(bias, 'y', 'imu.gyro_bias_rad_s')),
            float(_req(bias, 'z', 'imu.gyro_bias_rad_s')),
        ),
        silence_timeout_s=_positive(_req(d, 'silence_timeout_s', where), 'imu.silence_timeout_s'),
        stream_toggle_retry_s=_positive(
            _req(d, 'stream_toggle_retry_s', where), 'imu.stream_toggle_retry_s'
        ),
        required=bool(d.get('required', True)),
        frame_id=str(d.get('frame_id', 'imu_link')),
        frozen_after_s=_non_negative(d.get('frozen_after_s', 0.0), 'imu.frozen_after_s'),
        kalman=KalmanConfig(
            process_k1=_positive(_req(k, 'process_k1', 'imu.kalman'), 'process_k1'),
            process_k1b=_positive(_req(k, 'process_k1b', 'imu.kalman'), 'process_k1b'),
            measurement_noise_angle=_positive(
                _req(k, 'measurement_noise_angle', 'imu.kalman'), 'measurement_noise_angle'
            ),
            measurement_noise_rate=_positive(
                _req(k, 'measurement_noise_rate', 'imu.kalman'), 'measurement_noise_rate'
            ),
            init_samples=int(_req(k, 'init_samples', 'imu.kalman')),
            bias_process_noise=_positive(
                _req(k, 'bias_process_noise', 'imu.kalman'), 'bias_process_noise'
            ),
            still_rate_rad_s=_positive(
                _req(k, 'still_rate_rad_s', 'imu.kalman'), 'still_rate_rad_s'
            ),
            still_rate_change_rad_s=_positive(
                _req(k, 'still_rate_change_rad_s', 'imu.kalman'), 'still_rate_change_rad_s'
            ),
            still_wait_s=_positive(_req(k, 'still_wait_s', 'imu.kalman'), 'still_wait_s'),
        ),
    )
    if cfg.bus not in buses:
        raise ConfigError(f'{where}: unknown bus {cfg.bus!r}')
    return cfg


def _parse_powercube(d: Mapping, buses: Mapping) -> PowerCubeConfig:
    where = 'powercube'
    types = _req(d, 'module_types', where)
    joints = []
    seen_modules: set[tuple[str, int]] = set()
    for name, jd in _req(d, 'joints', where).items():
        w = f'{where}.joints.{name}'
        lower, upper = (float(x) for x in _req(jd, 'limits', w))
        if not (math.isfinite(lower) and math.isfinite(upper) and lower < upper):
            raise ConfigError(f'{w}: limits must be finite with lower < upper')
        tname = str(_req(jd, 'type', w))
        t = _req(types, tname, f'{where}.module_types')
        modules = []
        for i, md in enumerate(_req(jd, 'modules', w)):
            mw = f'{w}.modules[{i}]'
            m = PowerCubeModuleConfig(
                bus=str(_req(md, 'bus', mw)),
                module_id=int(_req(md, 'id', mw)),
                sign=_sign(md.get('sign', 1), mw),
            )
            if m.bus not in buses:
                raise ConfigError(f'{mw}: unknown bus {m.bus!r}')
            if not 1 <= m.module_id <= 0x1F:
                raise ConfigError(f'{mw}: Amtec module id {m.module_id} outside 1..31')
            if (m.bus, m.module_id) in seen_modules:
                raise ConfigError(f'{mw}: module {m.module_id} on {m.bus} used twice')
            seen_modules.add((m.bus, m.module_id))
            modules.append(m)
        if not modules:
            raise ConfigError(f'{w}: no modules')
        joints.append(
            BodyJointConfig(
                joint=str(name),
                lower=lower,
                upper=upper,
                module_type=tname,
                max_velocity_rad_s=math.radians(
                    _positive(_req(t, 'max_velocity_deg_s', tname), f'{tname} velocity')
                ),
                max_acceleration_rad_s2=math.radians(
                    _positive(_req(t, 'max_acceleration_deg_s2', tname), f'{tname} acceleration')
                ),
                modules=tuple(modules),
            )
        )
    return PowerCubeConfig(
        poll_rate_hz=_positive(_req(d, 'poll_rate_hz', where), 'poll_rate_hz'),
        silence_timeout_s=_positive(
            _req(d, 'silence_timeout_s', where), 'powercube.silence_timeout_s'
        ),
        required=bool(d.get('required', True)),
        joints=tuple(joints),
    )


def load_devices(
    path: str | Path | None = None, drive: Drivetrain | None = None
) -> CanDevicesConfig:
    """Load and validate a device map (default: `default_devices_file()`) for the drive train
    `drive` (default: the robot's, `drivetrain(load_krang())`)."""
    path = Path(path) if path is not None else default_devices_file()
    drive = drive if drive is not None else drivetrain(load_krang())
    data, sources = _read_yaml(path)
    buses = {}
    for name, bd in _req(data, 'buses', str(path)).items():
        bd = dict(bd)
        buses[str(name)] = BusConfig(
            name=str(name),
            interface=str(_req(bd, 'interface', f'buses.{name}')),
            channel=str(_req(bd, 'channel', f'buses.{name}')),
            options=dict(bd.get('options', {}) or {}),
        )
    cfg = CanDevicesConfig(
        path=path.resolve(),
        dbc_path=(path.resolve().parent / str(_req(data, 'dbc_file', str(path)))).resolve(),
        buses=buses,
        wheels=_parse_wheels(
            _req(data, 'wheels', str(path)), buses, drive, sources.get('wheels', path)
        ),
        imu=_parse_imu(_req(data, 'imu', str(path)), buses),
        powercube=_parse_powercube(_req(data, 'powercube', str(path)), buses),
    )
    names = cfg.joint_names
    if len(set(names)) != len(names):
        raise ConfigError('a joint name appears twice')
    if not cfg.dbc_path.exists():
        raise ConfigError(f'DBC file not found: {cfg.dbc_path}')
    return cfg
