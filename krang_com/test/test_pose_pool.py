"""The safe balanced pose pool: limits, balance, and collisions checked independently of
pinocchio."""

import json
import subprocess
import sys
import xml.etree.ElementTree as ET

import coal
import numpy as np
import pytest

from krang_model.com import base_to_frame0, x_com
from krang_model.kinematics import body_placements
from krang_model.poses import load_poses
from krang_model.robot import KRANG_POSE_COLUMNS, load_krang
from krang_pose_server.pool import PosePool, pool_config


@pytest.fixture(scope='module')
def robot():
    return load_krang()


@pytest.fixture(scope='module')
def pool(robot):
    return PosePool(robot)


@pytest.fixture(scope='module')
def generated(pool):
    return pool.generate(300, seed=4)


def _rpy(r, p, y):
    cx, sx, cy, sy, cz, sz = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return (
        np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
        @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        @ np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    )


class IndependentChecker:
    """Collision shapes straight from the URDF XML, placed with krang_model's numpy kinematics,
    tested
    pair by pair with coal.collide; the floor by the lowest box corner in frame 0."""

    def __init__(self, robot):
        self.robot = robot
        root = ET.parse(robot.urdf_path).getroot()
        # (body index, local rotation, local translation, coal shape, half extents)
        self.shapes = []
        for i, name in enumerate(robot.body_names):
            for col in root.findall(f"link[@name='{name}']/collision"):
                o = col.find('origin')
                xyz = np.array([float(v) for v in o.get('xyz').split()])
                rot = _rpy(*[float(v) for v in o.get('rpy').split()])
                g = col.find('geometry')
                if g.find('box') is not None:
                    half = np.array([float(v) for v in g.find('box').get('size').split()]) / 2
                    shape = coal.Box(*(2 * half))
                else:
                    c = g.find('cylinder')
                    rad, length = float(c.get('radius')), float(c.get('length'))
                    half = None
                    shape = coal.Cylinder(rad, length)
                self.shapes.append((i, rot, xyz, shape, half))
        parent = {}
        for j in root.findall('joint'):
            parent[j.find('child').get('link')] = j.find('parent').get('link')
        names = robot.body_names
        self.adjacent = {
            frozenset((names.index(c), names.index(p)))
            for c, p in parent.items()
            if c in names and p in names
        }
        self.wheels = set(robot.wheel_body_ids)

    def _placed(self, joints):
        rot, trans = body_placements(self.robot, joints[None])
        out = []
        for i, r_loc, t_loc, shape, half in self.shapes:
            R = rot[0, i] @ r_loc
            t = trans[0, i] + rot[0, i] @ t_loc
            out.append((i, R, t, shape, half))
        return out

    def self_collisions(self, joints):
        placed = self._placed(joints)
        hits = []
        for a in range(len(placed)):
            for b in range(a + 1, len(placed)):
                ia, ib = placed[a][0], placed[b][0]
                if frozenset((ia, ib)) in self.adjacent:
                    continue
                req, res = coal.CollisionRequest(), coal.CollisionResult()
                ta = coal.Transform3s(placed[a][1], placed[a][2])
                tb = coal.Transform3s(placed[b][1], placed[b][2])
                if coal.collide(placed[a][3], ta, placed[b][3], tb, req, res):
                    hits.append((self.robot.body_names[ia], self.robot.body_names[ib]))
        return hits

    def lowest_point(self, q_base, joints):
        """Lowest z (frame 0) of the non-wheel boxes."""
        R0 = base_to_frame0(q_base)[0]
        low = np.inf
        signs = np.array(
            [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float
        )
        for i, R, t, shape, half in self._placed(joints):
            if i in self.wheels or half is None:
                continue
            corners = t + (signs * half) @ R.T
            low = min(low, float((corners @ R0.T)[:, 2].min()))
        return low


@pytest.fixture(scope='module')
def checker(robot):
    return IndependentChecker(robot)


def test_poses_within_limits_and_balanced(robot, pool, generated):
    cfg = pool_config()
    j, q = generated.joints, generated.q_base
    assert j.shape == (300, 16)
    assert np.all(j >= np.array(cfg['sampling_lower'])) and np.all(
        j <= np.array(cfg['sampling_upper'])
    )
    assert np.all(j >= robot.lower) and np.all(j <= robot.upper)
    lo, hi = cfg['q_base_limits']
    assert np.all((q >= lo) & (q <= hi))
    assert np.abs(x_com(robot, q, j, robot.nominal_beta)).max() < 1e-12
    # the CoM is above the axle, not below
    from krang_model.com import com_frame0

    assert np.all(com_frame0(robot, q, j, robot.nominal_beta)[:, 2] > 0)
    assert generated.tries >= 300


def test_poses_are_collision_free_by_an_independent_check(robot, checker, generated):
    for qb, jt in zip(generated.q_base[:120], generated.joints[:120]):
        assert checker.self_collisions(jt) == []
        assert checker.lowest_point(qb, jt) > -robot.wheel_radius


def test_excluded_pairs_are_the_adjacent_links(pool, checker, robot):
    excluded = {
        frozenset((a.rsplit('_', 1)[0], b.rsplit('_', 1)[0]))
        for a, b in pool.checker.excluded_pairs
    }
    adjacent = {frozenset(robot.body_names[i] for i in pair) for pair in checker.adjacent}
    with_geometry = {robot.body_names[s[0]] for s in checker.shapes}
    assert excluded == {p for p in adjacent if p <= with_geometry}


def _find(pool, checker, robot, want, seed=0, max_batches=40):
    """A random pose, balanced and within the floor limits, with the wanted kind of collision
    according
    to the independent checker."""
    rng = np.random.default_rng(seed)
    for _ in range(max_batches):
        joints = rng.uniform(pool.lower, pool.upper, size=(256, 16))
        q_base, ok = pool.balanced_candidates(joints)
        for qb, jt in zip(q_base[ok], joints[ok]):
            self_hits = checker.self_collisions(jt)
            floor_hit = checker.lowest_point(qb, jt) < -robot.wheel_radius - 1e-6
            if want == 'self' and self_hits and not floor_hit:
                return qb, jt, self_hits
            if want == 'floor' and floor_hit and not self_hits:
                return qb, jt, []
    pytest.fail(f'no {want}-colliding pose found')


def test_a_self_colliding_pose_is_rejected(robot, pool, checker):
    qb, jt, hits = _find(pool, checker, robot, 'self', seed=1)
    assert not pool.is_safe(qb, jt)
    names = {
        frozenset((a.rsplit('_', 1)[0], b.rsplit('_', 1)[0]))
        for a, b in pool.checker.colliding_pairs(qb, jt)
    }
    assert {frozenset(h) for h in hits} <= names


def test_floor_check(robot, pool, checker):
    qb, jt, _ = _find(pool, checker, robot, 'floor', seed=2)
    assert not pool.is_safe(qb, jt)
    pairs = pool.checker.colliding_pairs(qb, jt)
    assert pairs and all('floor' in p for p in pairs)
    # the same pose checked without the floor is free
    from krang_pose_server.pool import CollisionChecker

    assert CollisionChecker(robot, check_floor=False).is_free(qb, jt)
    # the wheels rest on the floor and never count as a floor collision
    assert pool.checker.is_free(-0.5, np.zeros(16)) == (
        checker.self_collisions(np.zeros(16)) == []
        and checker.lowest_point(-0.5, np.zeros(16)) > -robot.wheel_radius
    )


def test_agreement_on_random_candidates(robot, pool, checker):
    rng = np.random.default_rng(9)
    joints = rng.uniform(pool.lower, pool.upper, size=(150, 16))
    q_base, ok = pool.balanced_candidates(joints)
    for qb, jt in zip(q_base[ok], joints[ok]):
        ind = (
            not checker.self_collisions(jt) and checker.lowest_point(qb, jt) > -robot.wheel_radius
        )
        assert pool.checker.is_free(qb, jt) == ind


def test_cli_pool(tmp_path, robot):
    out = tmp_path / 'pool.csv'
    res = subprocess.run(
        [
            sys.executable,
            '-m',
            'krang_cli.main',
            'poses',
            'pool',
            '--n',
            '200',
            '--seed',
            '3',
            '--out',
            str(out),
            '--no-progress',
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert doc['poses'] == 200 and doc['tries'] >= 200 and doc['seconds'] > 0
    q, j, _ = load_poses(out, KRANG_POSE_COLUMNS)
    assert len(q) == 200
    # 9 significant digits in the CSV
    assert np.abs(x_com(robot, q, j, robot.nominal_beta)).max() < 1e-8
