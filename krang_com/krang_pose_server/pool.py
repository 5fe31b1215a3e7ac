"""The pool of random safe and balanced poses the pose filter chooses from (paper §II-B).

A pose of the pool is
- within the sampling box of the authors' pose generator (config/poses.yaml), which lies
  inside the hardware joint limits;
- balanced under the "real" beta: q_base is the closed-form balance pitch
  (krang_model.com.balance_pitch), so x_com = 0 exactly, with the CoM above the axle; and q_base
  lies within the floor limits;
- safe: no self-collision between the URDF collision shapes (adjacent links, which always touch,
  and pairs touching at the neutral pose are excluded) and no shape below the floor, the plane
  z = -wheel_radius of frame 0 (the wheels themselves rest on it and are excluded).

Sampling is vectorised: joints are drawn in batches, the balance pitch and the floor limits are
evaluated for the whole batch with numpy, and only the surviving candidates go through pinocchio's
collision check (coal), one configuration at a time.
"""

import time
from dataclasses import dataclass, field

import coal
import numpy as np
import pinocchio as pin

from krang_model.com import balance_pitch, base_to_frame0
from krang_model.config import load_config
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang


def pool_config():
    """The `pool` section of config/poses.yaml (a copy)."""
    return dict(load_config('poses.yaml')['pose_server']['ros__parameters']['pool'])


@dataclass
class PoolResult:
    q_base: np.ndarray  # (N,)
    joints: np.ndarray  # (N, 16) pose order
    tries: int  # joint samples drawn
    seconds: float
    rejected: dict = field(default_factory=dict)  # reason -> count


class CollisionChecker:
    """Self- and floor-collision of a pose, with pinocchio's geometry model of the URDF's collision
    shapes.

    The geometry lives in the base frame (the model is fixed at Base); the floor is a
    coal.Halfspace whose placement in the base frame is R0(q_base)^T (rotation from frame 0), set
    per configuration.
    """

    def __init__(self, robot=None, margin=0.0, check_floor=True):
        self.robot = robot or load_krang()
        model = self.robot.model
        self.data = model.createData()
        gm = pin.buildGeomFromUrdf(model, str(self.robot.urdf_path), pin.GeometryType.COLLISION)
        if margin:
            for g in gm.geometryObjects:
                g.geometry = _inflate(g.geometry, margin)
        self.robot_geoms = [g.name for g in gm.geometryObjects]
        self.wheel_geoms = {
            i
            for i, g in enumerate(gm.geometryObjects)
            if model.frames[g.parentFrame].name in self.robot.wheels
        }
        gm.addAllCollisionPairs()
        # Pairs that always touch: joint-adjacent links, and anything touching at the neutral pose.
        q0 = pin.neutral(model)
        gd = pin.GeometryData(gm)
        pin.computeCollisions(model, self.data, gm, gd, q0, False)
        self.excluded_pairs = []
        for k in reversed(range(len(gm.collisionPairs))):
            cp = gm.collisionPairs[k]
            a, b = gm.geometryObjects[cp.first], gm.geometryObjects[cp.second]
            adjacent = (
                model.parents[a.parentJoint] == b.parentJoint
                or model.parents[b.parentJoint] == a.parentJoint
                or a.parentJoint == b.parentJoint
            )
            if adjacent or gd.collisionResults[k].isCollision():
                self.excluded_pairs.append((a.name, b.name))
                gm.removeCollisionPair(cp)
        self.excluded_pairs.reverse()
        self.n_self_pairs = len(gm.collisionPairs)
        self.floor_id = None
        if check_floor:
            # Halfspace {x : n.x <= d}: the solid below the plane z = -r (frame 0), margin grows it
            # upwards.
            floor = coal.Halfspace(np.array([0.0, 0.0, 1.0]), -self.robot.wheel_radius + margin)
            self.floor_id = gm.addGeometryObject(
                pin.GeometryObject('floor', 0, 0, pin.SE3.Identity(), floor)
            )
            for i in range(len(self.robot_geoms)):
                if i not in self.wheel_geoms:
                    gm.addCollisionPair(pin.CollisionPair(i, self.floor_id))
        self.geom_model = gm
        self.geom_data = pin.GeometryData(gm)
        self._floor_object = gm.geometryObjects[self.floor_id] if check_floor else None
        self._q = pin.neutral(model)
        self._idx = [model.joints[j].idx_q for j in self.robot.pose_joint_ids]

    def _set(self, q_base, joints):
        self._q[self._idx] = joints
        if self._floor_object is not None:
            self._floor_object.placement = pin.SE3(base_to_frame0(q_base)[0].T, np.zeros(3))

    def is_free(self, q_base, joints):
        """True when the pose (base pitch, 16 joints) collides with neither itself nor the
        floor."""
        self._set(q_base, joints)
        return not pin.computeCollisions(
            self.robot.model, self.data, self.geom_model, self.geom_data, self._q, True
        )

    def colliding_pairs(self, q_base, joints):
        """Names of every colliding pair (for diagnostics and tests)."""
        self._set(q_base, joints)
        pin.computeCollisions(
            self.robot.model, self.data, self.geom_model, self.geom_data, self._q, False
        )
        out = []
        for k, cp in enumerate(self.geom_model.collisionPairs):
            if self.geom_data.collisionResults[k].isCollision():
                out.append(
                    (
                        self.geom_model.geometryObjects[cp.first].name,
                        self.geom_model.geometryObjects[cp.second].name,
                    )
                )
        return out


def _inflate(shape, margin):
    if isinstance(shape, coal.Box):
        return coal.Box(*(shape.halfSide * 2 + 2 * margin))
    if isinstance(shape, coal.Cylinder):
        return coal.Cylinder(shape.radius + margin, 2 * shape.halfLength + 2 * margin)
    raise TypeError(f'cannot inflate {type(shape).__name__}')


class PosePool:
    """Draws random safe and balanced poses. `real_beta` is the beta the poses are balanced
    under."""

    def __init__(self, robot=None, real_beta=None, config=None):
        self.robot = robot or load_krang()
        cfg = pool_config()
        cfg.update(config or {})
        self.config = cfg
        if list(cfg['joint_columns']) != list(KRANG_POSE_COLUMNS):
            raise ValueError(
                'config/poses.yaml: pool.joint_columns must be the pose order '
                f'{KRANG_POSE_COLUMNS}'
            )
        self.lower = np.asarray(cfg['sampling_lower'], dtype=float)
        self.upper = np.asarray(cfg['sampling_upper'], dtype=float)
        if np.any(self.lower < self.robot.lower - 1e-12) or np.any(
            self.upper > self.robot.upper + 1e-12
        ):
            raise ValueError('config/poses.yaml: the sampling box leaves the URDF joint limits')
        self.q_base_limits = tuple(float(v) for v in cfg['q_base_limits'])
        self.real_beta = (
            self.robot.nominal_beta if real_beta is None else np.asarray(real_beta, float)
        )
        self.checker = CollisionChecker(
            self.robot,
            margin=float(cfg.get('collision_margin_m', 0.0)),
            check_floor=bool(cfg.get('check_floor', True)),
        )
        self.batch_size = int(cfg.get('batch_size', 4096))

    def balanced_candidates(self, joints):
        """(q_base, mask): closed-form balance pitch of each joint row and whether it is within the
        floor limits (vectorised; no collision check)."""
        q_base = balance_pitch(self.robot, joints, self.real_beta)
        lo, hi = self.q_base_limits
        return q_base, (q_base >= lo) & (q_base <= hi)

    def within_limits(self, joints):
        joints = np.atleast_2d(joints)
        return np.all((joints >= self.lower) & (joints <= self.upper), axis=1)

    def is_safe(self, q_base, joints):
        lo, hi = self.q_base_limits
        return bool(
            lo <= q_base <= hi
            and self.within_limits(joints)[0]
            and self.checker.is_free(q_base, joints)
        )

    def path_clear(self, start, goal, beta=None, points=16) -> bool:
        """True when the straight joint line from `start` to `goal` (the pose server's move) stays
        free of self- and floor collision at `points` poses along it, the goal included, each at
        the balance pitch `beta` (default the pool's) predicts: the robot balances through the
        move, so a path between two safe poses can still drive a gripper into the floor on the
        way, and a pose that is safe at the pool's balance pitch need not be at the robot's."""
        start, goal = np.asarray(start, dtype=float), np.asarray(goal, dtype=float)
        u = np.linspace(0.0, 1.0, int(points) + 1)[1:]
        if u.size == 0:
            return True
        path = start + u[:, None] * (goal - start)
        beta = self.real_beta if beta is None else np.asarray(beta, float)
        q_base = balance_pitch(self.robot, path, beta)
        return all(self.checker.is_free(q, j) for q, j in zip(q_base, path))

    def generate(self, n, seed=0, progress=None, max_tries=None):
        """n poses (q_base (n,), joints (n, 16)). `progress(k)` is called with the number of new
        poses."""
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        max_tries = max_tries or 1000 * n + 10000
        q_out = np.empty(n)
        j_out = np.empty((n, len(self.lower)))
        got = tries = 0
        rejected = {'floor_limits': 0, 'collision': 0}
        while got < n:
            if tries >= max_tries:
                raise RuntimeError(f'pose pool: only {got} of {n} poses after {tries} tries')
            joints = rng.uniform(self.lower, self.upper, size=(self.batch_size, len(self.lower)))
            q_base, ok = self.balanced_candidates(joints)
            # Samples are consumed in order, so the pool does not depend on the batch size ... up
            # to the last batch, where the tries beyond the n-th accepted pose are not counted.
            new = 0
            for i in range(self.batch_size):
                tries += 1
                if not ok[i]:
                    rejected['floor_limits'] += 1
                    continue
                if not self.checker.is_free(q_base[i], joints[i]):
                    rejected['collision'] += 1
                    continue
                q_out[got] = q_base[i]
                j_out[got] = joints[i]
                got += 1
                new += 1
                if got == n:
                    break
            if progress and new:
                progress(new)
        return PoolResult(q_out, j_out, tries, time.perf_counter() - t0, rejected)


def generate_pool(n, seed=0, robot=None, real_beta=None, progress=None):
    """Convenience: PosePool(robot, real_beta).generate(n, seed, progress)."""
    return PosePool(robot, real_beta).generate(n, seed=seed, progress=progress)
