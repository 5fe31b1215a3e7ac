"""The full-body Krang in MuJoCo: physics that is not the controller's own reduced model.

The model is built from ``krang_model/krang.urdf`` at load time (MjSpec, static bodies kept, so
the Base keeps its 75.8 kg): all 25 links on a free base, the wheels rolling on a floor plane by
contact, the passive caster of krang_model/README.md on the Base, the wheel motors (Kt, gearbox,
rotor inertia, current limit, friction) and the 16 Schunk modules as position servos that follow
the modules' speed and acceleration ramps, so the arms' momentum acts on the body while they
move. The hidden ``true_beta`` sets every link's mass and CoM; the contact, integrator and servo
settings are in config/mujoco.yaml with the reason for each; docs/mujoco.md describes the model,
the settings and the figures.

Of the true robot's ``ModelTerms`` it applies the drive train (torque constant, current limit,
wheel-to-body viscous and Coulomb friction, rolling resistance, wheel radius, gravity and floor
slope), payloads and ``inertia_add``; it refuses (``UnsupportedTerm``) what only the reduced
equations can express (``extra_forces``, ``com_shift``) and drive-train fields that the URDF and
true_beta fix here. The reduced model's caster penalty and yaw friction have no counterpart: the
caster and the tyres are contacts. The command delay is the drives' stage in front of every
plant (``krang_sim.sensors.CommandDelay``); sensor-side terms are the sensor model's.

Conventions are krang_model's (krang_model/README.md): MuJoCo's world is frame 0 (x along the
first heading, z up from the floor), the Base is placed by ``krang_model.com.base_to_frame0``,
q_base is the pitch against gravity, and a positive wheel angle rolls the robot forward.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from krang_model.com import balance_pitch, base_to_frame0
from krang_model.config import load_config
from krang_model.drivetrain import drivetrain
from krang_model.effects import ModelTerms
from krang_model.wip import point_mass_beta

from .plant import Motion, Plant, Truth, UnsupportedTerm, register_plant
from .sensors import CommandDelay

try:
    import mujoco
except ImportError:  # pragma: no cover - exercised only without the optional dependency
    mujoco = None

#: nominal link masses below this (the massless gripper plates) keep their placeholder inertia:
#: scaled by a mass ratio it would be meaningless
_MIN_SCALED_MASS_KG = 1e-3
#: a joint counts as arrived when within this of its target (rad): above the sway of a servo-held
#: joint under the body's stick-slip limit cycle on a gearmotor chain (0.4 mrad seen), which at
#: 0.1 mrad read as a move every 3-4 s cycle and restarted the detector's window each time
ARRIVED_RAD = 1e-3


def mujoco_config(overrides=None):
    """config/mujoco.yaml with ``overrides`` ({section: {key: value}}) laid over it."""
    cfg = {k: dict(v) for k, v in load_config('mujoco.yaml').items()}
    for section, values in (overrides or {}).items():
        cfg.setdefault(section, {}).update(values)
    return cfg


def check_terms(robot, terms):
    """Refuse the terms this plant cannot reproduce (``UnsupportedTerm``)."""
    if terms.extra_forces:
        raise UnsupportedTerm(
            'extra_forces are generalised forces of the reduced WIP equations; the full-body '
            'plant has no such coordinates'
        )
    if terms.com_shift:
        raise UnsupportedTerm('com_shift moves the reduced body only; change true_beta instead')
    nominal = drivetrain(robot)
    for name in ('track_width', 'wheel_mass', 'wheel_inertia'):
        if getattr(terms.drive, name) != getattr(nominal, name):
            raise UnsupportedTerm(f'{name} comes from the URDF and true_beta in this plant')


def build_model(robot, true_beta, terms, dt, cfg):
    """The compiled MjModel (see the module docstring) and the true beta with any payload."""
    if mujoco is None:
        raise ImportError('the MuJoCo plant needs the `mujoco` package (pip install mujoco)')
    check_terms(robot, terms)
    drive = terms.drive
    spec = mujoco.MjSpec.from_file(str(robot.urdf_path))
    spec.compiler.fusestatic = False  # the Base has no joint to the world: fused, it would vanish
    _options(spec, drive, dt, cfg)
    beta = _set_inertials(spec, robot, true_beta, terms)
    _contacts(spec, robot, drive, cfg['contact'])
    _wheels(spec, robot, drive, cfg['drive_friction'])
    arm = cfg['arm_servos']
    for name in robot.pose_joints:
        spec.joint(name).armature = arm['armature_kgm2']
    spec.body('Base').add_freejoint()
    # Servo gains need each joint's inertia: compile once without the servos to read it.
    _servos(spec, robot, _joint_inertia(spec.compile(), robot), arm)
    return spec.compile(), beta


def _joint_inertia(m, robot, n_poses=64):
    """The largest inertia (kg m^2, armature included) each body joint sees with every other
    joint held, over poses drawn in the joint limits (fixed seed): its servo is tuned for the
    heaviest case and is faster, still well damped, when the arm folds."""
    d = mujoco.MjData(m)
    dofs = [m.jnt_dofadr[m.joint(j).id] for j in robot.pose_joints]
    qadr = [m.jnt_qposadr[m.joint(j).id] for j in robot.pose_joints]
    full = np.zeros((m.nv, m.nv))
    rng = np.random.default_rng(0)
    out = np.zeros(len(dofs))
    for _ in range(n_poses):
        d.qpos[qadr] = rng.uniform(robot.lower, robot.upper)
        mujoco.mj_fwdPosition(m, d)
        mujoco.mj_fullM(m, d, full)
        out = np.maximum(out, np.diag(full)[dofs])
    return out


def _options(spec, drive, dt, cfg):
    o, c = spec.option, cfg['integrator']
    o.timestep = dt
    o.integrator = getattr(mujoco.mjtIntegrator, f'mjINT_{c["integrator"].upper()}')
    o.cone = getattr(mujoco.mjtCone, f'mjCONE_{c["cone"].upper()}')
    o.impratio = c['impratio']
    o.noslip_iterations = c['noslip_iterations']
    o.solver = getattr(mujoco.mjtSolver, f'mjSOL_{c["solver"].upper()}')
    o.iterations = c['iterations']
    o.tolerance = c['tolerance']
    # a floor rising forward by alpha: gravity leans back in the floor's frame
    g, a = drive.gravity, drive.floor_slope
    o.gravity = [-g * math.sin(a), 0.0, -g * math.cos(a)]


def _set_inertials(spec, robot, true_beta, terms):
    """Masses and CoMs from true_beta; inertias about the CoM scaled with each link's mass (same
    shape, different density); payloads as point masses welded to their link; inertia_add about
    the axle on the Base (a thin disc in the Base's y-z plane)."""
    b4 = np.asarray(true_beta, dtype=float).reshape(-1, 4)
    if np.any(b4[:, 0] <= 0.0):
        raise ValueError('true_beta has a link without positive mass')
    for i, name in enumerate(robot.body_names):
        body = spec.body(name)
        m_nom = robot.nominal_beta[4 * i]
        scale = b4[i, 0] / m_nom if m_nom >= _MIN_SCALED_MASS_KG else 1.0
        inertia = robot.body_inertias[i] * scale
        if name == 'Base' and terms.inertia_add:
            inertia = inertia + terms.inertia_add * np.diag([1.0, 0.5, 0.5])
        body.explicitinertial = True
        body.mass = b4[i, 0]
        body.ipos = b4[i, 1:] / b4[i, 0]
        body.fullinertia = [
            inertia[0, 0],
            inertia[1, 1],
            inertia[2, 2],
            inertia[0, 1],
            inertia[0, 2],
            inertia[1, 2],
        ]
    beta = np.asarray(true_beta, dtype=float)
    for k, (link, point, kg) in enumerate(terms.payloads):
        if kg <= 0.0:
            continue
        load = spec.body(link).add_body(name=f'payload{k}', pos=list(point))
        load.explicitinertial = True
        load.mass = kg
        load.ipos = [0.0, 0.0, 0.0]
        load.inertia = [kg * 4e-4] * 3  # a 3 cm ball: a point mass for the dynamics
        beta = point_mass_beta(robot, beta, link, point, kg)
    return beta


def _contacts(spec, robot, drive, c):
    """Robot geoms touch the floor only (never each other); the Base box not at all; the caster
    is a frictionless sphere that wins the pair's condim."""
    for body in robot.body_names:
        for geom in spec.body(body).geoms:
            geom.contype, geom.conaffinity = 0, 1
            geom.friction = [c['robot_friction'], 0.005, 0.0001]
            if body == 'Base' and not c['base_collides']:
                geom.conaffinity = 0
            geom.solref, geom.solimp = c['solref'], c['solimp'] + [0.5, 2.0]
    floor = spec.worldbody.add_geom(
        name='floor', type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0.0, 0.0, 1.0]
    )
    floor.contype, floor.conaffinity = 1, 0
    floor.friction = [c['floor_friction'], 0.005, 0.0001]
    floor.solref, floor.solimp = c['solref'], c['solimp'] + [0.5, 2.0]
    # The caster (krang_model/README.md, Dynamics): its centre at distance d from the axle, at the
    # angle gamma in the Base's y-z plane that makes it touch the floor at the documented pitch
    # with the URDF wheels: d cos(q_c - gamma) = r_c - r0.
    d, rc = drive.caster_distance, drive.caster_radius
    gamma = drive.caster_pitch + math.acos((rc - drive.caster_pitch_wheel_radius) / d)
    caster = spec.body('Base').add_geom(
        name='caster',
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[rc, 0.0, 0.0],
        pos=[0.0, d * math.cos(gamma), d * math.sin(gamma)],
    )
    caster.contype, caster.conaffinity = 0, 1
    caster.condim, caster.priority = c['caster_condim'], c['caster_priority']
    caster.mass = 0.0
    caster.solref, caster.solimp = c['solref'], c['solimp'] + [0.5, 2.0]
    if c['wheel_shape'] != 'ellipsoid':
        raise ValueError(f'wheel_shape {c["wheel_shape"]!r}: only ellipsoid is supported')


def _wheels(spec, robot, drive, friction):
    """Tyres of the drive's radius (ellipsoids: one contact point), motors through Kt and the
    gearbox with the drive's current limit, the rotor inertia reflected through the gearbox,
    wheel-to-body viscous and Coulomb friction, and rolling resistance against the floor."""
    for wheel in robot.wheels:
        (tyre,) = spec.body(wheel).geoms
        half_width = tyre.size[1]  # the URDF cylinder's half length, along the axle
        tyre.type = mujoco.mjtGeom.mjGEOM_ELLIPSOID
        tyre.size = [drive.wheel_radius, drive.wheel_radius, half_width]
        (joint,) = spec.body(wheel).joints
        joint.armature = drive.gear_ratio**2 * drive.rotor_inertia
        joint.damping = [drive.viscous_friction / 2.0, 0.0, 0.0]  # the drive's is both wheels'
        joint.frictionloss = drive.coulomb_friction  # per wheel: dry friction that sticks
        joint.solref_friction = friction['solref']
        joint.solimp_friction = friction['solimp'] + [0.5, 2.0]
        joint.actfrclimited = mujoco.mjtLimited.mjLIMITED_FALSE  # the current limit bounds it
        motor = spec.add_actuator(name=f'motor_{wheel}', target=joint.name)
        motor.trntype = mujoco.mjtTrn.mjTRN_JOINT
        motor.set_to_motor()
        motor.gear[0] = drive.torque_constant * drive.gear_ratio
        motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.ctrlrange = [-drive.current_limit, drive.current_limit]
    if drive.ground_viscous:
        # a torque on each tyre against its spin in the world (not relative to the body), with
        # its reaction on the floor: a site transmission without a reference site
        for wheel in robot.wheels:
            spec.body(wheel).add_site(name=f'tyre_{wheel}')
            roll = spec.add_actuator(name=f'rolling_{wheel}', target=f'tyre_{wheel}')
            roll.trntype = mujoco.mjtTrn.mjTRN_SITE
            roll.gear = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
            roll.gainprm[0] = 0.0
            roll.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            roll.biasprm[2] = -drive.ground_viscous / 2.0


def _servos(spec, robot, inertia, arm):
    """The Schunk modules' position loops: PID (kp = I w^2, kv = 2 zeta I w, ki = kp / T_i) on a
    position and a velocity setpoint (``ModuleRamps``), the module's torque limit from the URDF."""
    w = arm['bandwidth_rad_s']
    for name, m_jj in zip(robot.pose_joints, inertia):
        joint = spec.joint(name)
        kp = m_jj * w * w
        ki = kp / arm['integral_time_s']
        servo = spec.add_actuator(name=f'servo_{name}', target=name)
        servo.trntype = mujoco.mjtTrn.mjTRN_JOINT
        servo.set_to_pid(
            kp=kp,
            kv=2.0 * arm['damping_ratio'] * m_jj * w,
            ki=ki,
            imax=joint.actfrcrange[1] / ki,  # the integral alone never exceeds the module's torque
            ctrlspec=3,  # inputs: position and velocity setpoints
        )


@lru_cache(maxsize=None)
def module_acceleration_limits(joints):
    """Each joint's module acceleration limit (rad/s^2) from the device map (Schunk data)."""
    from krang_can_bridge.config import load_devices

    powercube = load_devices().powercube
    return np.array([powercube.joint(j).max_acceleration_rad_s2 for j in joints])


class ModuleRamps:
    """The setpoints the modules follow: towards the target at up to their speed and acceleration
    limits, braking to arrive at rest (a trapezoidal profile that a new target re-plans from the
    current speed), as a Schunk module in ramp mode moves."""

    def __init__(self, position, max_velocity, max_acceleration):
        self.position = np.array(position, dtype=float)
        self.velocity = np.zeros_like(self.position)
        self.max_velocity = np.asarray(max_velocity, dtype=float)
        self.max_acceleration = np.asarray(max_acceleration, dtype=float)

    def moving(self, target):
        return bool(np.any(self.position != target) or np.any(self.velocity))

    def advance(self, target, h):
        """Move on by `h` seconds; returns the mean (position, velocity) over the interval and
        whether any module is still moving."""
        p0, v0, a, ah = (
            self.position,
            self.velocity,
            self.max_acceleration,
            self.max_acceleration * h,
        )
        err = target - p0
        dist = np.abs(err)
        # the speed from which the module can still stop at the target
        v_des = np.copysign(np.minimum(self.max_velocity, np.sqrt(2.0 * a * dist)), err)
        v1 = v0 + np.clip(v_des - v0, -ah, ah)
        mean_v = 0.5 * (v0 + v1)
        p1 = p0 + mean_v * h
        # arrived (or would pass the target within the interval): at rest on it
        done = (dist <= np.abs(mean_v) * h) & (np.abs(v1) <= ah)
        if done.any():
            p1[done] = target[done]
            v1[done] = 0.0
        self.position, self.velocity = p1, v1
        return 0.5 * (p0 + p1), mean_v, not done.all()


@register_plant
class MujocoPlant(Plant):
    """Krang's full body in MuJoCo (module docstring). ``config``: overrides of
    config/mujoco.yaml, {section: {key: value}}."""

    name = 'mujoco'

    def __init__(self, robot, true_beta, joints, *, q_base=None, terms=None, dt=1e-3, config=None):
        self.robot = robot
        self.terms = terms if terms is not None else ModelTerms.nominal(drivetrain(robot))
        self.drive = self.terms.drive
        self.dt = float(dt)
        self.config = mujoco_config(config)
        self._build(true_beta)
        self.reset(joints, q_base)

    def _build(self, true_beta):
        self.model, self.true_beta = build_model(
            self.robot, true_beta, self.terms, self.dt, self.config
        )
        self.data = mujoco.MjData(self.model)
        m, robot = self.model, self.robot
        self._up = tuple(-np.asarray(m.opt.gravity) / np.linalg.norm(m.opt.gravity))
        self._base = m.body('Base').id
        wheel_joints = [m.body_jntadr[m.body(w).id] for w in robot.wheels]
        self._wheel_q = [int(m.jnt_qposadr[j]) for j in wheel_joints]
        self._wheel_v = [int(m.jnt_dofadr[j]) for j in wheel_joints]
        self._arm_q = np.array([m.jnt_qposadr[m.joint(j).id] for j in robot.pose_joints])
        self._arm_v = np.array([m.jnt_dofadr[m.joint(j).id] for j in robot.pose_joints])
        self._motor_ctrl = [m.actuator_ctrladr[m.actuator(f'motor_{w}').id] for w in robot.wheels]
        servos = [m.actuator(f'servo_{j}').id for j in robot.pose_joints]
        self._servo_pos = m.actuator_ctrladr[servos]  # each servo's controls: position, velocity
        self._servo_vel = self._servo_pos + 1
        self._ki = m.actuator_gainprm[servos, 0]
        self._integral = m.actuator_actadr[servos]
        self._gravity = np.array(m.opt.gravity)
        self._servo_steps = max(1, round(self.config['arm_servos']['update_period_s'] / self.dt))

    def set_true_beta(self, beta):
        """A new hidden mass model from now on (the payloads of the terms are added to it): the
        model is rebuilt and the state carried over."""
        old = self.data
        self._build(beta)
        d = self.data
        for name in ('qpos', 'qvel', 'act', 'ctrl', 'qacc_warmstart'):
            getattr(d, name)[:] = getattr(old, name)
        d.time = old.time
        mujoco.mj_forward(self.model, d)

    def reset(self, joints, q_base=None):
        """Put the robot down at rest, on its wheels at pitch `q_base` (None: sitting on the
        caster) in pose `joints`, at t = 0 and x = 0."""
        m, d = self.model, self.data
        d.qpos[:] = m.qpos0
        d.qvel[:] = 0.0
        d.act[:] = 0.0
        d.ctrl[:] = 0.0
        joints = np.clip(np.asarray(joints, dtype=float), self.robot.lower, self.robot.upper)
        pitch = self.drive.caster_contact_pitch if q_base is None else float(q_base)
        # pitch is against gravity; the free joint is placed in the floor's frame
        d.qpos[:3] = 0.0, 0.0, self.drive.wheel_radius
        self._place(d, pitch + self.drive.floor_slope)
        d.qpos[self._arm_q] = joints
        d.ctrl[self._servo_pos] = joints
        d.ctrl[self._servo_vel] = 0.0
        self.ramps = ModuleRamps(
            joints,
            self.robot.velocity_limit,
            module_acceleration_limits(self.robot.pose_joints),
        )
        # the modules start at rest where they are, their integrals holding them against gravity
        mujoco.mj_forward(m, d)
        d.act[self._integral] = d.qfrc_bias[self._arm_v] / self._ki
        self._settle()
        self.t = 0.0
        self.joint_targets = joints.copy()
        self._ramping = False
        self.applied_current = (0.0, 0.0)
        self._current_cmd = (0.0, 0.0)
        self._delay = CommandDelay(self.terms.actuation_delay, self.dt)
        self._wheel_zero = -pitch  # encoders read as the reduced plant's (phi = 0 at the start)
        self._x = 0.0
        self._xy = d.qpos[:2].copy()
        self._yaw = self._heading()

    def _settle(self, rounds=10, steps=5):
        """Let the tyres and the caster take the weight with the body held where it was put: the
        contacts start at zero penetration, where soft contacts carry nothing, and a robot put
        down there would first drop and bounce (a jolt its servos and its pitch would feel)."""
        m, d = self.model, self.data
        pose = d.qpos.copy()
        for _ in range(rounds):
            mujoco.mj_step(m, d, nstep=steps)
            z = d.qpos[2]
            d.qpos[:] = pose
            d.qpos[2] = z
            d.qvel[:] = 0.0
        d.time = 0.0
        mujoco.mj_forward(m, d)

    # --- commands -------------------------------------------------------------------------------
    def command_currents(self, left_a, right_a):
        self._current_cmd = (float(left_a), float(right_a))
        if not self._delay.active:
            self._apply_current(self._current_cmd)

    def _apply_current(self, current):
        lim = self.drive.current_limit
        self.applied_current = (min(max(current[0], -lim), lim), min(max(current[1], -lim), lim))
        self.data.ctrl[self._motor_ctrl] = self.applied_current

    def command_joints(self, targets):
        targets = np.clip(np.asarray(targets, dtype=float), self.robot.lower, self.robot.upper)
        self.joint_targets = targets
        self._ramping = self.ramps.moving(targets)

    # --- physics --------------------------------------------------------------------------------
    def step(self, n=1):
        n = int(n)
        if self._delay.active:  # the delayed current changes from one physics step to the next
            for _ in range(n):
                self._apply_current(self._delay.push(self._current_cmd))
                self._step(1)
            return
        self._step(n)

    def _step(self, n):
        m, d = self.model, self.data
        while n > 0 and self._ramping:
            # the setpoints advance every servo period, held in between
            k = min(n, self._servo_steps)
            pos, vel, self._ramping = self.ramps.advance(self.joint_targets, k * self.dt)
            d.ctrl[self._servo_pos], d.ctrl[self._servo_vel] = pos, vel
            mujoco.mj_step(m, d, nstep=k)
            n -= k
            self.t += k * self.dt
        if n > 0:
            mujoco.mj_step(m, d, nstep=n)
            self.t += n * self.dt
        # distance along the floor: the axle's displacement along the mean heading of the interval
        xy = self.data.qpos[:2]
        yaw = self._heading()
        self._yaw += _wrap(yaw - self._yaw)
        mid = self._yaw - 0.5 * _wrap(yaw - self._yaw)
        self._x += (xy[0] - self._xy[0]) * math.cos(mid) + (xy[1] - self._xy[1]) * math.sin(mid)
        self._xy = xy.copy()

    def push(self, pitch_rate):
        """A rotation of the body about the axle: the wheels keep their spin in the world."""
        v = self.data.qvel
        v[3] -= pitch_rate  # q_base turns about -x of the Base
        for i in self._wheel_v:
            v[i] -= pitch_rate

    @property
    def joints(self):
        return self.data.qpos[self._arm_q].copy()

    @property
    def joint_rates(self):
        """Body joint speeds (rad/s, pose order)."""
        return self.data.qvel[self._arm_v].copy()

    @property
    def joints_moving(self):
        """The modules still ramping, or a joint not yet within ARRIVED_RAD of its target."""
        return self.ramps.moving(self.joint_targets) or bool(
            np.any(np.abs(self.data.qpos[self._arm_q] - self.joint_targets) > ARRIVED_RAD)
        )

    # --- state ----------------------------------------------------------------------------------
    def _heading(self):
        """Yaw (rad, wrapped): the axle (Base x, to the right) is (sin psi, -cos psi, 0)."""
        x_axis = self.data.xmat[self._base][0::3]
        return math.atan2(x_axis[0], -x_axis[1])

    def _pitch(self):
        """q_base against gravity: Base y (up at q_base = 0) and Base z (backwards) against up."""
        r = self.data.xmat[self._base]
        ux, uy, uz = self._up
        return math.atan2(r[2] * ux + r[5] * uy + r[8] * uz, r[1] * ux + r[4] * uy + r[7] * uz)

    def specific_force(self):
        """What an accelerometer at the axle (the IMU frame's origin) feels, in the Base frame:
        the free joint's acceleration (its linear part is the Base origin's, in the world) minus
        gravity, from the last step. A sensor would cost MuJoCo a quarter of its step."""
        d = self.data
        f = d.qacc[:3] - self._gravity
        return tuple(float(v) for v in d.xmat[self._base].reshape(3, 3).T @ f)

    def motion(self):
        d = self.data
        gyro = d.qvel[3:6]  # the free joint's angular velocity is in the Base frame
        wl, wr = (d.qpos[i] + self._wheel_zero for i in self._wheel_q)
        rl, rr = (d.qvel[i] for i in self._wheel_v)
        return Motion(
            t=self.t,
            q_base=self._pitch(),
            dq_base=-float(gyro[0]),
            gyro=tuple(float(w) for w in gyro),
            specific_force=self.specific_force(),
            wheel_left=float(wl),
            wheel_right=float(wr),
            wheel_left_rate=float(rl),
            wheel_right_rate=float(rr),
            joints=self.joints,
            applied_current=self.applied_current,
        )

    def truth(self):
        d = self.data
        r = self.drive.wheel_radius
        q, dq = self._pitch(), -float(d.qvel[3])
        forward = d.qvel[0] * math.cos(self._yaw) + d.qvel[1] * math.sin(self._yaw)
        dpsi = float(d.xmat[self._base].reshape(3, 3)[2] @ d.qvel[3:6])  # world z of omega
        joints = self.joints
        return Truth(
            t=self.t,
            x_m=self._x,
            q_base=q,
            dq_base=dq,
            yaw=self._yaw,
            balance_pitch=float(balance_pitch(self.robot, joints[None], self.true_beta)[0]),
            state=(self._x / r, q, forward / r, dq, self._yaw, dpsi),
        )

    def wheel_pitch(self):
        qpos, qvel = self.data.qpos, self.data.qvel
        (ql, qr), (vl, vr), z = self._wheel_q, self._wheel_v, self._wheel_zero
        return (
            self.t,
            self._pitch(),
            -float(qvel[3]),
            float(qpos[ql]) + z,
            float(qpos[qr]) + z,
            float(qvel[vl]),
            float(qvel[vr]),
        )

    # --- checks ---------------------------------------------------------------------------------
    def total_mass(self):
        """MuJoCo's mass of the robot (kg): every body but the world."""
        return float(self.model.body_mass[1:].sum())

    def rest_balance_pitch(self, joints):
        """MuJoCo's own balance pitch of each pose (rows of `joints`) at rest: the pitch at which
        a servo holding the Base about the axle needs zero torque.

        The torque is MuJoCo's generalised gravity force (``qfrc_bias`` at rest, from its own
        kinematics of the URDF and recursive Newton-Euler) on the free joint's rotation about
        the Base x axis, through the axle. It is A sin q + B cos q in the pitch, so two pitches
        give its zeros; of the two, the one with MuJoCo's CoM (``subtree_com``) above the axle."""
        m = self.model
        d = mujoco.MjData(m)
        slope = self.drive.floor_slope
        out = []
        for pose in np.atleast_2d(np.asarray(joints, dtype=float)):
            d.qpos[self._arm_q] = pose
            d.qpos[:3] = 0.0, 0.0, 1.0
            torque = []
            for q in (0.5 * math.pi, 0.0):
                self._place(d, q + slope)
                mujoco.mj_forward(m, d)
                torque.append(d.qfrc_bias[3])
            root = math.atan2(-torque[1], torque[0])
            self._place(d, root + slope)
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            up = d.subtree_com[self._base] - d.xpos[self._base]
            out.append(root if up @ self._up > 0.0 else _wrap(root + math.pi))
        return np.array(out)

    @staticmethod
    def _place(d, floor_pitch):
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, base_to_frame0(floor_pitch)[0].ravel())
        d.qpos[3:7] = quat


def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi
