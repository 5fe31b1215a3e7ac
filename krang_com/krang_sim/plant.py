"""The plant interface: what a simulated Krang is, whichever physics engine moves it.

A plant is the true robot behind the devices. It takes what the drives and the PowerCube modules
are asked for (wheel motor currents, body joint targets), advances its physics, and reports the
true motion that the sensor model (``krang_sim.sensors``) turns into what the devices report. The
closed loop (``krang_sim.closed_loop``), the CAN device emulators (``sim_krang``) and the offline
campaigns talk to a plant only through this interface, so a new engine plugs in beside the others
the way python-can's bus backends do: subclass ``Plant``, give it a ``name`` and register it with
``register_plant``; ``make_plant(name, ...)`` builds one.

A plant is parameterised by the physical effects of ``krang_model.effects`` (one vocabulary for
the simulator, the replay and the discrepancy workflow): ``terms`` is the ``ModelTerms`` of the
true robot (its drive train, payloads, command delay, sensor offsets). A plant applies the
physical terms it models and refuses, with ``UnsupportedTerm``, a term it cannot reproduce.
Sensor-side terms (IMU pitch bias, joint encoder offsets) are the sensor model's, and the command
delay is the drive's (``krang_sim.sensors.CommandDelay``): both are common to every plant.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import numpy as np

from krang_model.drivetrain import drivetrain
from krang_model.effects import ModelTerms, model_terms


class UnsupportedTerm(ValueError):
    """The plant cannot reproduce a term of the model it was given (e.g. an extra force that only
    exists as a formula of the reduced model)."""


@dataclass
class Motion:
    """The true motion of the robot at one instant: what an ideal sensor set would report.

    Angles follow ``krang_model`` (q_base: the base's pitch, -pi/2 upright-ish, the sitting pitch
    on the caster about -1.76 rad); wheel angles are relative to the body, as the drives'
    encoders measure them."""

    t: float
    q_base: float  # pitch of the base (rad)
    dq_base: float  # its rate (rad/s)
    gyro: tuple  # angular velocity in the IMU (base) frame (rad/s)
    specific_force: tuple  # specific force at the IMU in its frame (m/s^2)
    wheel_left: float  # wheel angle relative to the body (rad)
    wheel_right: float
    wheel_left_rate: float  # (rad/s)
    wheel_right_rate: float
    joints: np.ndarray  # body joint angles (rad, robot.pose_joints order)
    applied_current: tuple  # motor currents the drives apply after clamping (A)


@dataclass
class Truth:
    """What only a simulator knows: for evaluation and logs, never for control."""

    t: float
    x_m: float  # distance the axle travelled along the floor (m)
    q_base: float  # true pitch (rad)
    dq_base: float
    yaw: float  # heading (rad)
    balance_pitch: float  # the q_base at which the robot as it is now balances (rad)
    state: tuple  # the reduced WIP state (phi, q_base, dphi, dq_base, psi, dpsi)


class Plant(abc.ABC):
    """One simulated Krang. Commands, then ``step(n)``, then read ``motion()`` / ``truth()``.

    Every plant is built as ``Plant(robot, true_beta, joints, *, q_base=None, terms=None,
    dt=1e-3, **engine_options)``: the hidden mass model, the starting pose (sitting on the caster
    when ``q_base`` is None) and the true robot's ``ModelTerms`` (None: nominal)."""

    #: registry key (``plant: reduced`` in config, ``--plant`` on the command line)
    name: str = ''

    robot: object  # krang_model.robot.KrangRobot
    dt: float  # physics step (s)
    t: float  # simulated time (s)
    joints: np.ndarray  # true body joint angles (rad, pose order)
    joint_targets: np.ndarray  # targets as commanded (clamped to the limits)

    @abc.abstractmethod
    def command_currents(self, left_a: float, right_a: float) -> None:
        """Motor currents the drives are asked for (A); the drives clamp them at their limit."""

    @abc.abstractmethod
    def command_joints(self, targets) -> None:
        """Body joint position targets (rad, pose order), clamped to the URDF limits; the
        modules move there at their speed limits."""

    @abc.abstractmethod
    def step(self, n: int = 1) -> None:
        """Advance ``n`` physics steps of ``dt``."""

    @abc.abstractmethod
    def motion(self) -> Motion:
        """The true motion now (the sensor model's input)."""

    @abc.abstractmethod
    def truth(self) -> Truth:
        """The simulator's truth now (evaluation only)."""

    @abc.abstractmethod
    def push(self, pitch_rate: float) -> None:
        """A push: add ``pitch_rate`` (rad/s) to the body's pitch rate at once."""

    @property
    def joints_moving(self) -> bool:
        return bool(np.any(np.abs(self.joint_targets - self.joints) > 1e-9))

    def wheel_pitch(self) -> tuple:
        """(t, q_base, dq_base, wheel_left, wheel_right, wheel_left_rate, wheel_right_rate): the
        part of ``motion()`` the controller's sample reads besides ``joints`` and
        ``joints_moving``. A plant may override it to give these without building a ``Motion``
        (the offline closed loop's hot path)."""
        m = self.motion()
        return (
            m.t,
            m.q_base,
            m.dq_base,
            m.wheel_left,
            m.wheel_right,
            m.wheel_left_rate,
            m.wheel_right_rate,
        )


PLANTS: dict[str, type[Plant]] = {}


def register_plant(cls: type[Plant]) -> type[Plant]:
    """Class decorator: make ``cls`` available as ``make_plant(cls.name, ...)``."""
    if not cls.name:
        raise ValueError(f'{cls.__name__} has no name')
    PLANTS[cls.name] = cls
    return cls


def make_plant(name: str, robot, true_beta, joints, **kwargs) -> Plant:
    """The plant registered as ``name`` (its module is imported on first use), built for the
    robot with the hidden ``true_beta`` sitting in pose ``joints``."""
    if name not in PLANTS:
        _import_builtin(name)
    try:
        cls = PLANTS[name]
    except KeyError:
        raise ValueError(f'unknown plant {name!r} (known: {", ".join(sorted(PLANTS))})') from None
    return cls(robot, true_beta, joints, **kwargs)


def terms_from_strings(robot, items) -> ModelTerms:
    """The true robot's ``ModelTerms`` from ``'key=value'`` strings (a node parameter, a command
    line): effect keys or names of ``krang_model.effects`` and values in the effect's unit, applied
    in order on the nominal model."""
    return model_terms(effect_pairs(items), ModelTerms.nominal(drivetrain(robot)))


def effect_pairs(items) -> list:
    """``[(key, value), ...]`` from ``'key=value'`` strings."""
    pairs = []
    for item in items:
        key, sep, value = str(item).partition('=')
        if not sep:
            raise ValueError(f"{item!r} is not 'key=value'")
        pairs.append((key.strip(), float(value)))
    return pairs


#: the built-in plants and the module that registers each (imported lazily: MuJoCo is optional
#: for the reduced plant's users)
BUILTIN = {'reduced': 'krang_sim.reduced_plant', 'mujoco': 'krang_sim.mujoco_plant'}


def _import_builtin(name):
    import importlib

    module = BUILTIN.get(name)
    if module is not None:
        importlib.import_module(module)


def plant_terms(robot, effects=(), model_file=None) -> ModelTerms:
    """The true robot's ``ModelTerms`` as a command line or a node gives them: the extended
    model of ``model_file`` (an ``extended_model.yaml`` written by `krang discrepancy`; None or ''
    = the nominal model), then the ``'key=value'`` ``effects`` applied on top of it, in order."""
    if not model_file:
        return terms_from_strings(robot, effects)
    from krang_discrepancy.extended_model import load_extended_model

    return model_terms(effect_pairs(effects), load_extended_model(model_file))
