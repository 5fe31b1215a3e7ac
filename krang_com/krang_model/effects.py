"""The vocabulary of physical effects: named, parameterised departures of the robot from the
nominal WIP model, each with a physical meaning and a unit. Plants, the discrepancy replay and the
discrepancy workflow all apply effects from this one registry.

An effect changes terms of the model (``ModelTerms``): a field of its ``Drivetrain`` (the physical
parameters of ``krang_model.wip``), the body (payloads, joint encoder offsets), the sensors (IMU
pitch bias) or the command timing (actuation delay). ``model_terms({'torque_constant': 0.9,
'floor_slope': 0.01})`` gives the ``ModelTerms`` of a robot with those effects: a simulated plant
is built with them (``krang_sim.plant``, ``terms=``), ``krang_discrepancy.replay.Replay``
predicts measured signals under them, and ``krang discrepancy`` fits their values and writes them
to an extended model. ``apply_effects`` does the same from ``Effect`` objects (the fits' inner
loop).

Built-in effects (``name``: value unit, meaning):

- ``imu_pitch_bias`` rad: the IMU reads q_base + bias (a pitch misalignment of the sensor)
- ``floor_slope`` rad: the floor rises along the heading (uphill forward is positive)
- ``wheel_radius`` m: effective rolling radius (the nominal one is the URDF's); it also moves the
  sitting pitch through the caster geometry (``Drivetrain.caster_contact_pitch``)
- ``payload`` kg: an unmodelled point mass rigidly on a named link, at a point of it
- ``wheel_viscous_friction`` N m s: extra wheel-to-body viscous friction (both wheels together)
- ``wheel_coulomb_friction`` N m: extra Coulomb friction per wheel (as ``krang_model.wip`` has it)
- ``torque_constant`` (scale true/nominal, reported in N m/A): true motor torque constant
- ``actuation_delay`` s: transport delay between the commanded and the applied wheel current
  (``krang_model.drivetrain.HeldCommand`` says what a delayed command is)
- ``encoder_offset`` rad: a body-joint encoder reads q + offset (default joint JWaist)
- ``rolling_resistance`` N m s: tyre rolling resistance, viscous in the ground speed

Optional effects (``register_optional_effects()``, ``krang discrepancy --extra-effects``):
body_inertia (kg m^2 about the axle), drive_current_limit (A), com_height (m). The per-effect
tests do not cover them; they serve the hardware data.

Adding your own effect
----------------------
Subclass ``Effect`` (or instantiate it) and register it; ``krang discrepancy --effects-module
my_effects`` (a module path or a .py file) imports your module before the run, so the decorator
runs::

    from krang_model.effects import Effect, register_effect

    # a term the model has no field for: an additive generalised force (N m) on the
    # wheel equation and on the pitch equation, evaluated on arrays of the predicted state
    @register_effect
    class PitchSpring(Effect):
        name = 'cable_spring'
        unit = 'N m/rad'
        bounds = (-200.0, 200.0)
        scale = 20.0
        description = 'a cable harness pulling the body back towards q_base = -1.55 rad'

        def apply(self, terms, value):
            terms.extra_forces.append(lambda s, k=value: (0.0 * s.q_base, -k * (s.q_base + 1.55)))

``s`` carries numpy arrays ``phi, q_base, dphi, dq_base, theta, tau`` (the applied total wheel
torque) and ``t``. Such a formula exists only for the reduced model: a plant that cannot apply a
term refuses it (``krang_sim.plant.UnsupportedTerm``).

An effect on a physical term changes a field of the drive train instead:
``terms.add_to_drive(ground_viscous=value)`` (``rolling_resistance``). A new physical term goes
into ``krang_model.wip.WipDynamics`` (its parameter a new field of
``krang_model.drivetrain.Drivetrain``); an effect then adds to it as above, and the plants, the
replay and the controller's design all see it.

Several variants of one physical effect (e.g. a payload on different links) share ``name`` and
differ in ``key``; the report and the JSON give the name plus the variant's ``detail``.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

from krang_model.drivetrain import Drivetrain, drivetrain
from krang_model.robot import load_krang

# ----------------------------------------------------------------------------- model terms


@lru_cache(maxsize=None)
def nominal_drive() -> Drivetrain:
    """Krang's drive train (krang_model.drivetrain): the nominal values of the effects."""
    return drivetrain(load_krang())


@dataclass
class ModelTerms:
    """The terms of the predicted model that effects may change (SI units): the drive train (the
    physical parameters of krang_model.wip) and what lies outside the equations of motion.
    ``ModelTerms.nominal(drive)`` is the nominal model."""

    drive: Drivetrain
    actuation_delay: float = 0.0  # s
    imu_pitch_bias: float = 0.0  # rad, measured = true + bias
    inertia_add: float = 0.0  # kg m^2 added to the body's inertia about the axle
    com_shift: float = 0.0  # m added to the body CoM distance from the axle
    payloads: tuple = ()  # ((link, (x, y, z) m in the link frame, kg), ...)
    joint_offsets: dict = field(default_factory=dict)  # joint name -> encoder offset (rad)
    extra_forces: list = field(default_factory=list)  # callables s -> (f_phi, f_qbase), N m

    @classmethod
    def nominal(cls, drive) -> 'ModelTerms':
        return cls(drive=drive)

    def copy(self) -> 'ModelTerms':
        new = copy.copy(self)
        new.joint_offsets = dict(self.joint_offsets)
        new.extra_forces = list(self.extra_forces)
        new.payloads = tuple(self.payloads)
        return new

    def add_to_drive(self, **amounts):
        """Add to fields of the drive train (the Drivetrain is immutable: replaced)."""
        added = {k: getattr(self.drive, k) + v for k, v in amounts.items()}
        self.drive = replace(self.drive, **added)

    def body_key(self):
        """Hashable description of what changes the reduced body (payloads, joint offsets)."""
        return (
            tuple((link, tuple(p), float(m)) for link, p, m in self.payloads),
            tuple(sorted((j, float(v)) for j, v in self.joint_offsets.items() if v)),
        )


# ----------------------------------------------------------------------------- effects


class Effect:
    """One named effect with one scalar parameter. Subclass and set the class attributes, or pass
    them to the constructor. ``apply(terms, value)`` changes ``terms`` in place."""

    name: str = ''
    unit: str = ''
    bounds: tuple = (-math.inf, math.inf)
    scale: float = 1.0
    nominal_value: float = 0.0  # the value at which the effect is absent
    description: str = ''

    def __init__(self, **attrs):
        for k, v in attrs.items():
            setattr(self, k, v)
        if not self.name:
            raise ValueError('an effect needs a name')

    # identity --------------------------------------------------------------------------------
    @property
    def key(self) -> str:
        """Unique id in the library: the name, plus the variant for variants (payload@lGripper)."""
        variant = self.variant()
        return f'{self.name}@{variant}' if variant else self.name

    def variant(self) -> str:
        return ''

    @property
    def detail(self) -> dict:
        """Extra facts about the variant (link, point, joint...) for the report and the JSON."""
        return {}

    # model -----------------------------------------------------------------------------------
    def apply(self, terms: ModelTerms, value: float) -> None:
        raise NotImplementedError

    def display(self, value: float, base: ModelTerms | None = None) -> tuple[float, str]:
        """The reported (value, unit) for a fitted parameter value applied on top of `base`
        (default: unchanged)."""
        return value, self.unit

    def display_scale(self, base: ModelTerms | None = None) -> float:
        """d(displayed value)/d(parameter), to convert the parameter's uncertainty."""
        return 1.0

    def __repr__(self):
        return f'<Effect {self.key} [{self.unit}]>'


class ImuPitchBias(Effect):
    name = 'imu_pitch_bias'
    unit = 'rad'
    bounds = (-0.3, 0.3)
    scale = 0.01
    description = (
        'the IMU reads q_base + bias: a pitch misalignment of the sensor (mimics a CoM error)'
    )

    def apply(self, terms, value):
        terms.imu_pitch_bias += value


class FloorSlope(Effect):
    name = 'floor_slope'
    unit = 'rad'
    bounds = (-0.25, 0.25)
    scale = 0.01
    description = 'the floor rises along the heading by this angle (uphill forward positive)'

    def apply(self, terms, value):
        terms.add_to_drive(floor_slope=value)


class WheelRadius(Effect):
    name = 'wheel_radius'
    unit = 'm'
    bounds = (0.18, 0.34)
    scale = 0.01
    description = 'effective rolling radius of the wheels (enters the inertia and the coupling)'

    def __init__(self, nominal_m: float | None = None, **attrs):
        super().__init__(**attrs)
        nominal = nominal_drive().wheel_radius if nominal_m is None else nominal_m
        self.nominal_value = float(nominal)

    def apply(self, terms, value):
        terms.drive = replace(terms.drive, wheel_radius=float(value))


class Payload(Effect):
    name = 'payload'
    unit = 'kg'
    bounds = (0.0, 40.0)
    scale = 1.0
    description = 'an unmodelled point mass rigidly attached to a link'

    def __init__(self, link: str = 'lGripper', point=(0.0, 0.0, 0.10), **attrs):
        super().__init__(**attrs)
        self.link = link
        self.point = tuple(float(v) for v in point)

    def variant(self):
        return self.link

    @property
    def detail(self):
        return {'link': self.link, 'point_m': list(self.point)}

    def apply(self, terms, value):
        terms.payloads = tuple(terms.payloads) + ((self.link, self.point, float(value)),)


class WheelViscousFriction(Effect):
    name = 'wheel_viscous_friction'
    unit = 'N m s'
    bounds = (-0.1, 30.0)
    scale = 0.5
    description = (
        'extra viscous friction between wheels and body (both wheels), on the relative speed'
    )

    def apply(self, terms, value):
        terms.add_to_drive(viscous_friction=value)


class WheelCoulombFriction(Effect):
    name = 'wheel_coulomb_friction'
    unit = 'N m'
    bounds = (0.0, 15.0)
    scale = 0.5
    description = (
        'extra Coulomb friction per wheel, a smooth sign (tanh, 0.01 rad/s) of the '
        'wheel-to-body speed, on the wheel equation as krang_model.wip models it'
    )

    def apply(self, terms, value):
        terms.add_to_drive(coulomb_friction=value)


class TorqueConstant(Effect):
    name = 'torque_constant'
    unit = 'N m/A'
    bounds = (0.1, 3.0)
    scale = 0.05
    nominal_value = 1.0
    description = (
        'motor torque constant: the fit estimates the scale true/nominal of the applied '
        'torque; reported as the true Kt at the motor'
    )

    def __init__(self, nominal_kt: float | None = None, **attrs):
        super().__init__(**attrs)
        nominal = nominal_drive().torque_constant if nominal_kt is None else nominal_kt
        self.nominal_kt = float(nominal)

    @property
    def detail(self):
        return {'nominal_kt_Nm_per_A': self.nominal_kt}

    def apply(self, terms, value):
        terms.drive = replace(terms.drive, torque_constant=terms.drive.torque_constant * value)

    def display(self, value, base=None):
        """The torque constant itself (N m/A): the scale times the Kt of the model it extends
        (a baseline may already have changed it)."""
        return value * self.display_scale(base), self.unit

    def display_scale(self, base=None):
        return self.nominal_kt if base is None else float(base.drive.torque_constant)


class ActuationDelay(Effect):
    name = 'actuation_delay'
    unit = 's'
    bounds = (0.0, 0.15)
    scale = 0.005
    description = 'transport delay between the commanded and the applied wheel torque'

    def apply(self, terms, value):
        terms.actuation_delay += value


class EncoderOffset(Effect):
    name = 'encoder_offset'
    unit = 'rad'
    bounds = (-0.3, 0.3)
    scale = 0.01
    description = 'a body-joint encoder reads q + offset (the model then reduces the wrong pose)'

    def __init__(self, joint: str = 'JWaist', **attrs):
        super().__init__(**attrs)
        self.joint = joint

    def variant(self):
        return self.joint

    @property
    def detail(self):
        return {'joint': self.joint}

    def apply(self, terms, value):
        terms.joint_offsets[self.joint] = terms.joint_offsets.get(self.joint, 0.0) + float(value)


class RollingResistance(Effect):
    name = 'rolling_resistance'
    unit = 'N m s'
    bounds = (0.0, 60.0)
    scale = 0.5
    description = (
        'tyre rolling resistance, viscous in the ground speed (wheel-to-ground, not wheel-to-body)'
    )

    def apply(self, terms, value):
        terms.add_to_drive(ground_viscous=value)


# ----------------------------------------------------------------------------- optional effects
# Not in the default library (the per-effect tests do not cover them); `krang discrepancy
# --extra-effects` or ``register_optional_effects()`` adds them.


class BodyInertia(Effect):
    name = 'body_inertia'
    unit = 'kg m^2'
    bounds = (-5.0, 60.0)
    scale = 1.0
    description = (
        'inertia about the axle missing from the model (the URDF rotational inertias of '
        'Base, Spine and Bracket are placeholders)'
    )

    def apply(self, terms, value):
        terms.inertia_add += value


class DriveCurrentLimit(Effect):
    name = 'drive_current_limit'
    unit = 'A'
    bounds = (3.0, 60.0)
    scale = 1.0
    description = (
        'the motor current where the drives really saturate (commanded currents are clamped there)'
    )

    def __init__(self, **attrs):
        super().__init__(**attrs)
        self.nominal_value = float(nominal_drive().current_limit)

    def apply(self, terms, value):
        terms.drive = replace(terms.drive, current_limit=float(value))


class ComHeight(Effect):
    name = 'com_height'
    unit = 'm'
    bounds = (-0.12, 0.5)
    scale = 0.01
    description = (
        'the body CoM is this much farther from the axle than the mass model says (same '
        'direction, point mass): balanced poses fix the CoM angle but not its distance'
    )

    def apply(self, terms, value):
        terms.com_shift += value


OPTIONAL_EFFECTS = (BodyInertia, DriveCurrentLimit, ComHeight)


def register_optional_effects():
    for cls in OPTIONAL_EFFECTS:
        register_effect(cls())


# ----------------------------------------------------------------------------- registry

#: key -> Effect: the library the naming step searches (in registration order).
EFFECTS: dict[str, Effect] = {}

#: the names of the built-in effects, which the `krang discrepancy --json` contract knows
#: (user-added names are allowed too)
BUILTIN_NAMES = (
    'imu_pitch_bias',
    'floor_slope',
    'wheel_radius',
    'payload',
    'wheel_viscous_friction',
    'wheel_coulomb_friction',
    'torque_constant',
    'actuation_delay',
    'encoder_offset',
    'rolling_resistance',
)


def register_effect(effect):
    """Add an effect to the library. Works as a decorator on an ``Effect`` subclass (instantiated
    with no arguments) or on a function returning an Effect, or called with an instance.
    Re-registering a key replaces the old entry. Returns its argument."""
    obj = effect
    if isinstance(effect, type):
        obj = effect()
    elif callable(effect) and not isinstance(effect, Effect):
        obj = effect()
    if not isinstance(obj, Effect):
        raise TypeError(f'register_effect needs an Effect, got {obj!r}')
    if not (obj.bounds[0] <= obj.nominal_value <= obj.bounds[1]):
        raise ValueError(
            f'{obj.key}: nominal value {obj.nominal_value} outside bounds {obj.bounds}'
        )
    EFFECTS[obj.key] = obj
    return effect


def unregister_effect(key: str) -> None:
    EFFECTS.pop(key, None)


def library(keys=None) -> list[Effect]:
    """The registered effects (all, or those whose key or name is in `keys`)."""
    if keys is None:
        return list(EFFECTS.values())
    wanted = set(keys)
    unknown = wanted - set(EFFECTS) - {e.name for e in EFFECTS.values()}
    if unknown:
        raise ValueError(f'unknown effects {sorted(unknown)}; known: {sorted(EFFECTS)}')
    return [e for e in EFFECTS.values() if e.key in wanted or e.name in wanted]


def get_effect(key: str) -> Effect:
    if key in EFFECTS:
        return EFFECTS[key]
    by_name = [e for e in EFFECTS.values() if e.name == key]
    if len(by_name) == 1:
        return by_name[0]
    raise KeyError(f'no effect {key!r} (known: {sorted(EFFECTS)})')


def load_effects_module(spec: str) -> None:
    """Import a module (dotted path) or a .py file so that its ``register_effect`` calls run."""
    import importlib
    import importlib.util
    from pathlib import Path

    path = Path(spec)
    if spec.endswith('.py') or path.exists():
        mod_spec = importlib.util.spec_from_file_location(path.stem, path)
        if mod_spec is None or mod_spec.loader is None:
            raise ValueError(f'cannot import effects from {spec}')
        module = importlib.util.module_from_spec(mod_spec)
        mod_spec.loader.exec_module(module)
    else:
        importlib.import_module(spec)


def apply_effects(terms: ModelTerms, effects, values) -> ModelTerms:
    """A copy of `terms` with each ``Effect`` applied at its value, in order."""
    out = terms.copy()
    for eff, v in zip(effects, values):
        eff.apply(out, float(v))
    return out


def model_terms(effects=(), base: ModelTerms | None = None) -> ModelTerms:
    """The ``ModelTerms`` of a robot with these effects: ``effects`` maps effect keys or names
    (``'torque_constant'``, ``'payload@rGripper'``) or ``Effect`` objects (a variant the library
    does not register, ``EncoderOffset('LJ2')``) to values in the effect's parameter unit, as a
    dict or as (key, value) pairs (a key may repeat: the effects apply in order, on top of each
    other). `base` defaults to the nominal model (``nominal_drive()``). How a plant, the replay
    and an extended-model file turn effect values into the model."""
    items = list(effects.items()) if isinstance(effects, dict) else list(effects)
    base = ModelTerms.nominal(nominal_drive()) if base is None else base
    effs = [k if isinstance(k, Effect) else get_effect(k) for k, _ in items]
    return apply_effects(base, effs, [v for _, v in items])


def _register_builtins():
    for eff in (
        ImuPitchBias(),
        FloorSlope(),
        WheelRadius(),
        Payload('lGripper', (0.0, 0.0, 0.10)),
        Payload('rGripper', (0.0, 0.0, 0.10)),
        WheelViscousFriction(),
        WheelCoulombFriction(),
        TorqueConstant(),
        ActuationDelay(),
        EncoderOffset('JWaist'),
        RollingResistance(),
    ):
        register_effect(eff)


_register_builtins()
