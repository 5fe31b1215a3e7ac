"""The one drive-train description: wheels from the URDF, motors, gearbox and contacts from
config/robot.yaml. Every user of a motor constant (controller, simulator, bridge, metrics,
discrepancy) reads it from here.

Its fields are also the physical parameters of the WIP equations (krang_model.wip) that are not the
body: the named effects of the simulator and of `krang discrepancy` (wheel radius, friction, floor
slope, torque constant) are values of these fields. A field may hold a numpy array: ``stack`` makes
one Drivetrain of P parameter sets that broadcasts in ``WipDynamics``. ``HeldCommand`` says how the
drives apply a sampled, delayed command."""

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from .config import robot_config


@dataclass(frozen=True)
class Drivetrain:
    wheel_radius: float  # m
    track_width: float  # m
    wheel_mass: float  # kg, both wheels
    wheel_inertia: float  # kg m^2, both wheels about the axle
    gear_ratio: float
    torque_constant: float  # N m / A, motor side
    rotor_inertia: float  # kg m^2, one motor
    current_limit: float  # A
    viscous_friction: float  # N m s, wheel relative to body, both wheels
    ground_viscous: float  # N m s, wheel relative to ground
    coulomb_friction: float  # N m per wheel
    yaw_friction: float  # N m s
    caster_pitch: float  # rad, IMU pitch on the caster with caster_pitch_wheel_radius, level floor
    caster_stiffness: float
    caster_damping: float
    caster_distance: float  # m, wheel axle to the caster wheel's centre
    caster_radius: float  # m, caster wheel
    caster_pitch_wheel_radius: float  # m, the wheel radius at which caster_pitch holds
    gravity: float = 9.81
    floor_slope: float = 0.0

    @property
    def reflected_rotor_inertia(self):
        return 2.0 * self.gear_ratio**2 * self.rotor_inertia

    @property
    def caster_contact_pitch(self):
        """IMU pitch (rad) at which the caster touches the floor. The wheels hold the axle one
        wheel radius r above the floor, so the caster wheel (radius r_c, centre d from the axle,
        fixed in the body) touches where d cos(q + slope - gamma) = r_c - r: a larger wheel tilts
        the body further back onto the caster (dq/dr = -1/sqrt(d^2 - (r - r_c)^2), the caster's
        horizontal lever arm), a floor rising forward tilts it back with the floor. gamma is fixed
        by ``caster_pitch`` at ``caster_pitch_wheel_radius`` on a level floor, so the nominal
        drive train touches at exactly ``caster_pitch`` (krang_model/README.md, Dynamics)."""
        r, r0 = self.wheel_radius, self.caster_pitch_wheel_radius
        acos = np.arccos if isinstance(r, np.ndarray) else math.acos
        rc, dist = self.caster_radius, self.caster_distance
        shift = acos((rc - r0) / dist) - acos((rc - r) / dist)
        return self.caster_pitch + shift - self.floor_slope


def stack(drives):
    """One Drivetrain of P parameter sets: a field that differs between them becomes a (P, 1)
    array (broadcasting against (P, S) states), a field they share stays a float."""
    out = {}
    for f in fields(Drivetrain):
        values = [getattr(d, f.name) for d in drives]
        same = all(v == values[0] for v in values)
        out[f.name] = values[0] if same else np.array(values, dtype=float)[:, None]
    return Drivetrain(**out)


def drivetrain(robot, **overrides):
    """The drive train from the URDF (wheels) and config/robot.yaml (motors, contacts)."""
    cfg = robot_config()
    d, c = cfg['drivetrain'], cfg['caster']
    wheel_ids = robot.wheel_body_ids
    nominal = robot.nominal_beta
    params = Drivetrain(
        wheel_radius=robot.wheel_radius,
        track_width=robot.track_width,
        wheel_mass=float(sum(nominal[4 * i] for i in wheel_ids)),
        wheel_inertia=float(sum(robot.body_inertias[i][0, 0] for i in wheel_ids)),
        gear_ratio=d['gear_ratio'],
        torque_constant=d['torque_constant_Nm_per_A'],
        rotor_inertia=d['rotor_inertia_kgm2'],
        current_limit=d['current_limit_A'],
        viscous_friction=d['viscous_friction_Nm_s'],
        ground_viscous=d['ground_viscous_Nm_s'],
        coulomb_friction=d['coulomb_friction_Nm'],
        yaw_friction=cfg['yaw']['viscous_friction_Nm_s'],
        caster_pitch=c['contact_pitch_rad'],
        caster_stiffness=c['stiffness_Nm_per_rad'],
        caster_damping=c['damping_Nm_s_per_rad'],
        caster_distance=c['wheel_centre_distance_m'],
        caster_radius=c['wheel_radius_m'],
        caster_pitch_wheel_radius=robot.wheel_radius,
        gravity=cfg['environment']['gravity_m_s2'],
        floor_slope=cfg['environment']['floor_slope_rad'],
    )
    return replace(params, **overrides)


@dataclass(frozen=True, eq=False)
class HeldCommand:
    """A sampled command (wheel currents or torques) as the drives apply it: each value holds from
    its time until the next one (zero-order hold), it takes effect ``delay`` seconds after it was
    sent (the actuation delay), and nothing is applied before the first value. The one definition
    of the actuation delay: the replay evaluates it on arrays of times; a plant stepping at ``dt``
    applies at step k the command sent ``command_delay_steps(delay, dt)`` steps earlier, which is
    ``applied(t_k, delay)`` with the delay rounded to the step."""

    t: np.ndarray  # (M,) times at which the values were sent (s, increasing)
    value: np.ndarray  # (M,) or (M, C): the value from each time on

    def __post_init__(self):
        t = np.asarray(self.t, float)
        v = np.asarray(self.value, float)
        if v.shape[:1] != t.shape:
            raise ValueError(f'{t.size} times for {v.shape[0] if v.ndim else 0} values')
        dt = np.diff(t).reshape((-1,) + (1,) * (v.ndim - 1))
        cum = np.concatenate([np.zeros((1,) + v.shape[1:]), np.cumsum(v[:-1] * dt, axis=0)])
        object.__setattr__(self, 't', t)
        object.__setattr__(self, 'value', v)
        object.__setattr__(self, '_cum', cum[: t.size])

    def _at(self, times, delay):
        """(index of the value in effect or -1, times since it was sent, mask shape helper)."""
        tt = np.asarray(times, float) - delay
        i = np.searchsorted(self.t, tt, side='right') - 1
        j = np.maximum(i, 0)
        none = (i < 0).reshape(i.shape + (1,) * (self.value.ndim - 1))
        return j, tt, none

    def applied(self, times, delay=0.0):
        """The value the drives apply at each of `times`."""
        if self.t.size == 0:
            return np.zeros(np.shape(times) + self.value.shape[1:])
        j, _, none = self._at(times, delay)
        return np.where(none, 0.0, self.value[j])

    def integral(self, times, delay=0.0):
        """The running integral of the applied value from the first value's effect to each of
        `times`, exact for the held steps (the replay's sub-step averages are its differences)."""
        if self.t.size == 0:
            return np.zeros(np.shape(times) + self.value.shape[1:])
        j, tt, none = self._at(times, delay)
        since = (tt - self.t[j]).reshape(none.shape)
        return np.where(none, 0.0, self._cum[j] + self.value[j] * since)


def command_delay_steps(delay, dt):
    """Whole steps of `dt` by which a stepping plant delays its commands (``HeldCommand``)."""
    return int(round(delay / dt))
