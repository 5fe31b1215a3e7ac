"""Synthetic records: what a session of the simulated Krang logs, with hidden effects.

``simulate_record`` is a scenario on the one closed loop (``krang_sim.closed_loop.ClosedLoop``):
the plant with hidden effects (``krang_model.effects``: effect values, or ``ModelTerms``) under
the ADRC ``BalanceController`` with the nominal model; sit -> stand up -> balance, pose changes, a
current excitation, optionally sit down. The record it returns is what the session logged and
carries no trace of the effects. ``Unmodelled`` adds effects outside the library, made around the
loop (its sample and command hooks), to test the ``unexplained`` answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from krang_adrc_controller.controller import ControllerConfig
from krang_adrc_controller.modes import HARDWARE_STAND_SETTLE_S, MODE_CODES
from krang_model.beta import load_beta
from krang_model.config import config_path
from krang_model.drivetrain import drivetrain
from krang_model.effects import EncoderOffset, ModelTerms, model_terms
from krang_model.robot import load_krang
from krang_model.wip import point_mass_beta
from krang_sim.closed_loop import ClosedLoop
from krang_sim.scenarios import TABLE2_POSE

from .record import Record, resample


#: a default pose programme for simulate_record: joint deltas (rad) from the start pose, in
#: pose order (JWaist, JTorso, LJ1..LJFT, RJ1..RJFT); each held for a few seconds in turn
DEFAULT_POSE_PROGRAMME = (
    {'LJ1': 0.6, 'LJ2': 0.5, 'JWaist': -0.12},
    {'RJ1': -0.6, 'RJ2': -0.5, 'JTorso': 0.5, 'LJ4': 0.6},
    {'JWaist': -0.25, 'LJ2': -0.4, 'RJ4': -0.6},
    {},
)

#: how much further back (rad) than the hardware's the records' stand window reaches: a hidden
#: floor slope or larger wheels tilt the sitting robot back with the caster geometry, and the
#: hardware's -12 deg window (the Table II pose sits at -11.2 deg) would refuse to stand on a
#: 0.02 rad slope
STAND_WINDOW_EXTRA_RAD = 0.1


def record_controller_config(overrides: dict | None = None) -> ControllerConfig:
    """The controller the synthetic records are made with: the dataclass defaults, not
    config/controller.yaml (test data must not change when the deployed controller is retuned);
    the paper's law and the stand-up's settle time as on the hardware runs (no balance-point
    observer, 3.33 s); the stand window ``STAND_WINDOW_EXTRA_RAD`` wider; then `overrides`
    (dotted names)."""
    base = ControllerConfig()
    values = {
        'balance_point.enabled': False,
        'modes.stand_settle_s': HARDWARE_STAND_SETTLE_S,
        'modes.stand_error_min_rad': base.modes.stand_error_min_rad - STAND_WINDOW_EXTRA_RAD,
    }
    values.update(overrides or {})
    return base.override(values)


@dataclass(frozen=True)
class Unmodelled:
    """Effects outside the library, applied around the simulated plant (all zero = none)."""

    drive_deadband_a: float = 0.0  # the drives deliver nothing below this current, i - d beyond
    gyro_scale: float = 0.0  # the gyro reads (1 + s) x the pitch rate (scale factor)
    payload_growth_kg_s: float = 0.0  # a mass on lGripper (0, 0, 0.10) m growing from the start
    # the left drive delivers (1 + x), the right (1 - x) of its current: a left/right drive
    # difference that turns the robot (lateral motion the averaged wheel signals do not show)
    current_imbalance: float = 0.0

    def current(self, i: float) -> float:
        d = self.drive_deadband_a
        return i if d <= 0 else math.copysign(max(abs(i) - d, 0.0), i)

    def currents(self, il: float, ir: float) -> tuple[float, float]:
        """What the two drives deliver for the commanded (il, ir)."""
        x = self.current_imbalance
        return self.current(il) * (1.0 + x), self.current(ir) * (1.0 - x)


class _Session:
    """The operator and the logger of ``simulate_record``, as the closed loop's hooks: enable
    after 1 s, the pose programme once balanced, the current excitation, the sit-down, the
    unmodelled effects; every control step logged."""

    def __init__(
        self,
        loop,
        truth,
        pose0,
        steps,
        *,
        programme,
        hold_s,
        excitation_a,
        seconds,
        sit_down,
        unmodelled,
        seed,
    ):
        self.loop, self.truth, self.pose0 = loop, truth, pose0
        self.prog = [dict(p) for p in programme]
        self.hold_s, self.excitation_a, self.seconds = hold_s, excitation_a, seconds
        self.sit_down, self.um = sit_down, unmodelled
        self.rng = np.random.default_rng(seed + 7919)
        self.k = 0
        self.exc, self.exc_until = 0.0, 0.0
        self.t_balance = None
        self.next_pose_t = math.inf
        self.sat_down = False
        self.grow_next = 0.0
        self.log = {k: np.empty(steps) for k in ('t', 'q', 'r', 'w', 'wr', 'il', 'ir', 'mode')}
        self.joints = np.empty((steps, len(pose0)))

    def before_control(self, s):
        """The sample hook: the growing payload, the operator's enable, the gyro scale."""
        loop, um = self.loop, self.um
        plant, ctl = loop.plant, loop.controller
        if um.payload_growth_kg_s and plant.t >= self.grow_next:  # re-reduce the heavier body
            kg = um.payload_growth_kg_s * plant.t
            plant.set_true_beta(
                point_mass_beta(loop.robot, self.truth, 'lGripper', (0.0, 0.0, 0.10), kg)
            )
            self.grow_next = plant.t + 0.1
        if self.k * ctl.h >= 1.0 and not ctl.enabled and not self.sat_down:
            ctl.set_enabled(True)
        if um.gyro_scale:
            s = replace(s, pitch_rate=s.pitch_rate * (1.0 + um.gyro_scale))
        return s

    def after_control(self, t, s, out, currents):
        """The command hook: pose moves, sit-down, excitation, deadband; the step's log."""
        loop, robot = self.loop, self.loop.robot
        plant, ctl = loop.plant, loop.controller
        if out.mode == 'balance' and self.t_balance is None:
            self.t_balance = t
            self.next_pose_t = t + 1.5
        if t >= self.next_pose_t and not self.sat_down:
            if self.prog:
                delta = self.prog.pop(0)
                target = self.pose0.copy()
                for jn, v in delta.items():
                    target[robot.pose_joints.index(jn)] += v
                plant.command_joints(target)
                self.next_pose_t = (
                    t
                    + self.hold_s
                    + float(np.max(np.abs(target - plant.joints) / robot.velocity_limit))
                )
            else:
                self.next_pose_t = math.inf
        if (
            self.sit_down
            and not self.sat_down
            and t >= self.seconds - 6.0
            and out.mode == 'balance'
        ):
            if not plant.joints_moving and np.allclose(plant.joint_targets, self.pose0):
                ctl.request_sit()
                self.sat_down = True
            elif not np.allclose(plant.joint_targets, self.pose0):
                plant.command_joints(self.pose0)
        il, ir = currents
        if out.mode == 'balance' and self.excitation_a:
            if t >= self.exc_until:
                self.exc = self.excitation_a * self.rng.choice([-1.0, 1.0])
                self.exc_until = t + self.rng.uniform(0.1, 0.5)
            il, ir = il + self.exc, ir + self.exc
        log, k = self.log, self.k
        log['t'][k], log['q'][k], log['r'][k] = s.t, s.q_base, s.pitch_rate
        log['w'][k] = 0.5 * (s.wheel_left + s.wheel_right)
        log['wr'][k] = 0.5 * (s.wheel_left_rate + s.wheel_right_rate)
        log['il'][k], log['ir'][k] = il, ir
        log['mode'][k] = MODE_CODES.get(out.mode, -2)
        self.joints[k] = s.joints
        self.k = k + 1
        return self.um.currents(il, ir)


def simulate_record(
    effects=None,
    *,
    seconds: float = 30.0,
    seed: int = 0,
    start_pose=None,
    programme=DEFAULT_POSE_PROGRAMME,
    hold_s: float = 3.0,
    excitation_a: float = 3.0,
    noise=None,
    log_rate_hz: float | None = None,
    sit_down: bool | None = None,
    controller_config=None,
    true_beta=None,
    controller_beta=None,
    name: str = 'sim',
    unmodelled: Unmodelled | None = None,
    plant: str = 'reduced',
    plant_options: dict | None = None,
) -> Record:
    """A measured-looking record of a session on the closed loop, with hidden ``effects`` in the
    plant: effect values (``{'torque_constant': 0.9}``, see ``krang_model.effects.model_terms``)
    or the true robot's ``ModelTerms``. The controller is the BalanceController with the NOMINAL
    model (``record_controller_config``, or `controller_config`), or with `controller_beta`.

    Sequence: sit on the caster for 1 s, enable (stand up, then balance), after 1.5 s of balance go
    through ``programme`` (pose changes, each held ``hold_s``), with a random +-``excitation_a`` A
    telegraph added to both wheel currents while balancing; if ``sit_down`` (default: records of
    20 s or more) return to the start pose and sit down for the last part. The record logs what the
    controller and the hardware would: the noisy sensor samples (``noise``: the sensors'
    ``krang_sim.sensors.SensorNoise``) at the controller rate (or ``log_rate_hz``) and the
    commanded currents (controller output + excitation) as wheel torques, every control step.
    Nothing in the record says which effect was hidden. ``unmodelled``: effects outside the
    library (drive deadband, gyro scale factor, growing payload, left/right drive imbalance).
    ``plant``: a registered plant; ``plant_options``: more keywords of it (the MuJoCo plant's
    ``config``, e.g. softer tyre contacts)."""
    robot = load_krang()
    beta = load_beta(config_path('sim_true_beta.yaml'), robot)
    truth = beta if true_beta is None else np.asarray(true_beta, float)
    pose0 = np.array(TABLE2_POSE if start_pose is None else start_pose, float)
    terms = (
        effects
        if isinstance(effects, ModelTerms)
        else model_terms(effects or {}, ModelTerms.nominal(drivetrain(robot)))
    )
    loop = ClosedLoop(
        robot,
        truth,
        beta if controller_beta is None else np.asarray(controller_beta, float),
        pose0,
        controller_config=controller_config or record_controller_config(),
        plant=plant,
        terms=terms,
        noise=noise,
        seed=seed,
        log_rate_hz=0.0,
        plant_options=plant_options,
    )
    um = unmodelled or Unmodelled()
    if um.payload_growth_kg_s and not hasattr(loop.plant, 'set_true_beta'):
        raise ValueError(f'a growing payload needs a plant with set_true_beta, not {plant!r}')
    ctl = loop.controller
    steps = int(round(seconds / ctl.h))
    session = _Session(
        loop,
        truth,
        pose0,
        steps,
        programme=programme,
        hold_s=hold_s,
        excitation_a=excitation_a,
        seconds=seconds,
        sit_down=seconds >= 20.0 if sit_down is None else sit_down,
        unmodelled=um,
        seed=seed,
    )
    loop.sample_hook = session.before_control
    loop.command_hook = session.after_control
    loop.run(seconds)
    log, joints = session.log, session.joints
    t = log['t']
    k_motor = ctl.k_motor
    cmd = np.column_stack([log['il'], log['ir']]) * k_motor
    if log_rate_hz:
        grid = np.arange(t[0], t[-1] + 1e-12, 1.0 / log_rate_hz)
        pick = lambda v: np.interp(grid, t, v)  # noqa: E731
        meas = dict(
            t=grid,
            q_base=pick(log['q']),
            pitch_rate=pick(log['r']),
            wheel=pick(log['w']),
            wheel_rate=pick(log['wr']),
            joints=resample(t, joints, grid),
        )
    else:
        meas = dict(
            t=t,
            q_base=log['q'],
            pitch_rate=log['r'],
            wheel=log['w'],
            wheel_rate=log['wr'],
            joints=joints,
        )
    return Record(
        **meas,
        cmd_t=t,
        cmd_torque=cmd,
        torque_limit=ctl.drive.current_limit * k_motor,
        name=name,
        source='krang_sim',
        kind='sim',
        meta={
            'controller_rate_hz': 1.0 / ctl.h,
            'mode': log['mode'],
            'mode_t': t.copy(),
            'seconds': seconds,
            'seed': seed,
            'stood_up_s': session.t_balance,
        },
    )


# ------------------------------------------------------------------------- validation suite
# (case id, hidden effects {key: parameter value}, Unmodelled kwargs, seed, noise factor,
# {expected effect name: true parameter value}, other acceptable answers). Expected 'none' for no
# effect and 'unexplained' for effects outside the library, unless a physically equivalent library
# effect is listed as acceptable. The true values are in the effects' parameter units (a torque
# constant as the scale true/nominal; ``Effect.display`` gives the reported value); the workflow is
# told none of this.
VALIDATION_SUITE = (
    ('none seed 11', {}, {}, 11, 1.0, {}, ()),
    ('none seed 12', {}, {}, 12, 1.0, {}, ()),
    ('none seed 13, noise x2', {}, {}, 13, 2.0, {}, ()),
    ('none seed 14, noise x0.5', {}, {}, 14, 0.5, {}, ()),
    ('small floor_slope', {'floor_slope': 0.003}, {}, 21, 1.0, {'floor_slope': 0.003}, ()),
    (
        'small imu_pitch_bias',
        {'imu_pitch_bias': 0.004},
        {},
        22,
        1.0,
        {'imu_pitch_bias': 0.004},
        (),
    ),
    ('small payload', {'payload@lGripper': 1.0}, {}, 23, 1.0, {'payload': 1.0}, ()),
    (
        'small torque_constant',
        {'torque_constant': 0.95},
        {},
        24,
        1.0,
        {'torque_constant': 0.95},
        (),
    ),
    (
        'small actuation_delay',
        {'actuation_delay': 0.008},
        {},
        25,
        1.0,
        {'actuation_delay': 0.008},
        (),
    ),
    (
        'small wheel_coulomb_friction',
        {'wheel_coulomb_friction': 0.8},
        {},
        26,
        1.0,
        {'wheel_coulomb_friction': 0.8},
        (),
    ),
    ('small wheel_radius', {'wheel_radius': 0.258}, {}, 27, 1.0, {'wheel_radius': 0.258}, ()),
    (
        'small encoder_offset',
        {'encoder_offset@JWaist': 0.012},
        {},
        28,
        1.0,
        {'encoder_offset': 0.012},
        (),
    ),
    (
        'small rolling_resistance',
        {'rolling_resistance': 1.0},
        {},
        29,
        1.0,
        {'rolling_resistance': 1.0},
        (),
    ),
    (
        'pair torque_constant + wheel_radius',
        {'torque_constant': 0.85, 'wheel_radius': 0.25},
        {},
        31,
        1.0,
        {'torque_constant': 0.85, 'wheel_radius': 0.25},
        (),
    ),
    (
        'pair floor_slope + actuation_delay',
        {'floor_slope': 0.015, 'actuation_delay': 0.02},
        {},
        32,
        1.0,
        {'floor_slope': 0.015, 'actuation_delay': 0.02},
        (),
    ),
    (
        'pair payload + wheel_coulomb_friction',
        {'payload@lGripper': 5.0, 'wheel_coulomb_friction': 2.0},
        {},
        33,
        1.0,
        {'payload': 5.0, 'wheel_coulomb_friction': 2.0},
        (),
    ),
    (
        'pair viscous + imu_pitch_bias',
        {'wheel_viscous_friction': 2.0, 'imu_pitch_bias': 0.02},
        {},
        34,
        1.0,
        {'wheel_viscous_friction': 2.0, 'imu_pitch_bias': 0.02},
        (),
    ),
    ('out: drive deadband 2 A', {}, {'drive_deadband_a': 2.0}, 41, 1.0, {}, ()),
    ('out: gyro scale factor +10 %', {}, {'gyro_scale': 0.1}, 42, 1.0, {}, ()),
    (
        'out: LJ2 (arm) encoder offset 0.1 rad',
        {EncoderOffset('LJ2'): 0.1},
        {},
        43,
        1.0,
        {},
        ('payload',),
    ),
    ('out: payload growing 0.3 kg/s', {}, {'payload_growth_kg_s': 0.3}, 44, 1.0, {}, ('payload',)),
)


# ------------------------------------------------------------------ records of the MuJoCo plant
#: the full-body plant's contacts 4x softer than config/mujoco.yaml's (MuJoCo's default time
#: constant, 0.02 s): tyre (and caster) compliance, which the reduced model has no term for
SOFT_TYRES = {'config': {'contact': {'solref': [0.02, 1.0]}}}

#: Hidden-effect records of the full-body MuJoCo plant (physics that is not the workflow's): the
#: VALIDATION_SUITE's fields plus the keywords of ``simulate_record`` (plant, programme, plant
#: options). The library's effects at sizes no other suite or test uses, three pairs, no-effect
#: records with the pose programme and with the poses held, and effects the reduced model lacks:
#: the body's internal momentum while the waist, torso and arms move (in every record with the
#: pose programme), a left/right drive imbalance that turns the robot, softer tyres. The expected
#: answers follow the suite's convention: with the pose programme the internal momentum is always
#: hidden too, so a record is in the library only with the poses held. The MuJoCo plant does not
#: apply an actuation delay (bench/bench_discrepancy.py, ``NOT_APPLIED``): its delay cases are
#: records without a delay, scored so.
_MJ = {'plant': 'mujoco'}
_HELD = {'plant': 'mujoco', 'programme': ()}
MUJOCO_SUITE = (
    ('mujoco none seed 51', {}, {}, 51, 1.0, {}, (), _MJ),
    ('mujoco none seed 52, noise x2', {}, {}, 52, 2.0, {}, (), _MJ),
    ('mujoco none seed 53, poses held', {}, {}, 53, 1.0, {}, (), _HELD),
    ('mujoco none seed 54, poses held, noise x0.5', {}, {}, 54, 0.5, {}, (), _HELD),
    (
        'mujoco imu_pitch_bias',
        {'imu_pitch_bias': -0.013},
        {},
        55,
        1.0,
        {'imu_pitch_bias': -0.013},
        (),
        _MJ,
    ),
    ('mujoco floor_slope', {'floor_slope': -0.011}, {}, 56, 1.0, {'floor_slope': -0.011}, (), _MJ),
    (
        'mujoco wheel_radius',
        {'wheel_radius': 0.279},
        {},
        57,
        1.0,
        {'wheel_radius': 0.279},
        (),
        _MJ,
    ),
    ('mujoco payload', {'payload@rGripper': 3.5}, {}, 58, 1.0, {'payload': 3.5}, (), _MJ),
    (
        'mujoco wheel_viscous_friction',
        {'wheel_viscous_friction': 2.7},
        {},
        59,
        1.0,
        {'wheel_viscous_friction': 2.7},
        (),
        _MJ,
    ),
    (
        'mujoco wheel_coulomb_friction',
        {'wheel_coulomb_friction': 1.3},
        {},
        60,
        1.0,
        {'wheel_coulomb_friction': 1.3},
        (),
        _MJ,
    ),
    (
        'mujoco torque_constant',
        {'torque_constant': 0.78},
        {},
        61,
        1.0,
        {'torque_constant': 0.78},
        (),
        _MJ,
    ),
    (
        'mujoco actuation_delay',
        {'actuation_delay': 0.035},
        {},
        62,
        1.0,
        {'actuation_delay': 0.035},
        (),
        _MJ,
    ),
    (
        'mujoco encoder_offset',
        {'encoder_offset@JWaist': -0.045},
        {},
        63,
        1.0,
        {'encoder_offset': -0.045},
        (),
        _MJ,
    ),
    (
        'mujoco rolling_resistance',
        {'rolling_resistance': 5.5},
        {},
        64,
        1.0,
        {'rolling_resistance': 5.5},
        (),
        _MJ,
    ),
    (
        'mujoco pair torque_constant + floor_slope',
        {'torque_constant': 0.88, 'floor_slope': 0.012},
        {},
        65,
        1.0,
        {'torque_constant': 0.88, 'floor_slope': 0.012},
        (),
        _MJ,
    ),
    (
        'mujoco pair payload + actuation_delay',
        {'payload@lGripper': 4.5, 'actuation_delay': 0.025},
        {},
        66,
        1.0,
        {'payload': 4.5, 'actuation_delay': 0.025},
        (),
        _MJ,
    ),
    (
        'mujoco pair viscous + wheel_radius',
        {'wheel_viscous_friction': 3.2, 'wheel_radius': 0.256},
        {},
        67,
        1.0,
        {'wheel_viscous_friction': 3.2, 'wheel_radius': 0.256},
        (),
        _MJ,
    ),
    (
        'mujoco out: left/right drive imbalance 10 %',
        {},
        {'current_imbalance': 0.1},
        68,
        1.0,
        {},
        (),
        _MJ,
    ),
    (
        'mujoco out: left/right drive imbalance 10 %, poses held',
        {},
        {'current_imbalance': 0.1},
        69,
        1.0,
        {},
        (),
        _HELD,
    ),
    (
        'mujoco out: soft tyres, poses held',
        {},
        {},
        70,
        1.0,
        {},
        (),
        {**_HELD, 'plant_options': SOFT_TYRES},
    ),
)
