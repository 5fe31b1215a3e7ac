"""The robot as pinocchio parses it from our URDF: bodies, joints, limits and the beta layout.

Everything downstream (phi, the WIP reduction, the pose pool, the simulator) reads the robot from
here, so the URDF stays the one source of truth.
"""

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

PACKAGE_DIR = Path(__file__).resolve().parent
KRANG_URDF = PACKAGE_DIR / 'krang.urdf'
WIP7_URDF = PACKAGE_DIR / 'wip7.urdf'

# The authors' body order (krang_data/README.md): beta entry 4*i + k is body i, quantity k.
KRANG_BODIES = (
    'Base',
    'LWheel',
    'RWheel',
    'Spine',
    'Bracket',
    'L1',
    'L2',
    'L3',
    'L4',
    'L5',
    'L6',
    'lGripper',
    'lgPlate1',
    'lgPlate2',
    'R1',
    'R2',
    'R3',
    'R4',
    'R5',
    'R6',
    'rGripper',
    'rgPlate1',
    'rgPlate2',
)
# Pose order of the hardware CSVs: waist, torso, left arm 1..7, right arm 1..7.
KRANG_POSE_JOINTS = (
    'JWaist',
    'JTorso',
    'LJ1',
    'LJ2',
    'LJ3',
    'LJ4',
    'LJ5',
    'LJ6',
    'LJFT',
    'RJ1',
    'RJ2',
    'RJ3',
    'RJ4',
    'RJ5',
    'RJ6',
    'RJFT',
)
KRANG_POSE_COLUMNS = (
    ('q_waist', 'q_torso')
    + tuple(f'q_left_{i}' for i in range(1, 8))
    + tuple(f'q_right_{i}' for i in range(1, 8))
)
BETA_QUANTITIES = ('m', 'm*x', 'm*y', 'm*z')


@dataclass(frozen=True)
class JointChain:
    """Per pinocchio joint (index 1..n): parent index, placement in parent and unit axis."""

    parents: np.ndarray  # (njoints,) int, parents[0] = 0 (universe)
    rotations: np.ndarray  # (njoints, 3, 3) jointPlacement rotation
    translations: np.ndarray  # (njoints, 3)
    axes: np.ndarray  # (njoints, 3) revolute axis in the joint frame


class RobotModel:
    """A fixed-base pinocchio model rooted at the body whose origin is the wheel-axle midpoint.

    `pose_joints` are the joints a pose sets (in pose order); other joints (the wheels) stay at 0
    for kinematics, which is exact because the wheel CoMs lie on their own axes.
    """

    def __init__(self, urdf_path, bodies, pose_joints, name, wheels=('LWheel', 'RWheel')):
        self.name = name
        self.wheels = tuple(wheels)
        self.urdf_path = Path(urdf_path)
        self.model = pin.buildModelFromUrdf(str(self.urdf_path))
        self.body_names = tuple(bodies)
        self.pose_joints = tuple(pose_joints)
        self.n_bodies = len(self.body_names)
        self.n_beta = 4 * self.n_bodies
        self.chain = _joint_chain(self.model)
        self._joint_id = {self.model.names[j]: j for j in range(1, self.model.njoints)}
        unknown = [j for j in self.pose_joints if j not in self._joint_id]
        if unknown:
            raise ValueError(f'{self.urdf_path.name}: pose joints not in the URDF: {unknown}')
        self.pose_joint_ids = [self._joint_id[j] for j in self.pose_joints]
        self.body_frames = []
        for body in self.body_names:
            if not self.model.existFrame(body, pin.FrameType.BODY):
                raise ValueError(f'{self.urdf_path.name}: body {body!r} not in the URDF')
            self.body_frames.append(
                self.model.frames[self.model.getFrameId(body, pin.FrameType.BODY)]
            )
        self._urdf = ET.parse(self.urdf_path).getroot()
        self.nominal_beta, self.body_inertias = self._inertials_from_urdf()
        self.wheel_body_ids = [self.body_names.index(w) for w in self.wheels]
        self.wheel_radius, self.track_width = self._wheel_geometry()
        self.nominal_mass = float(self.nominal_beta[0::4].sum())
        lower, upper = [], []
        for j in self.pose_joint_ids:
            idx = self.model.joints[j].idx_q
            lower.append(self.model.lowerPositionLimit[idx])
            upper.append(self.model.upperPositionLimit[idx])
        self.lower = np.array(lower)
        self.upper = np.array(upper)
        self.velocity_limit = np.array(
            [self.model.velocityLimit[self.model.joints[j].idx_v] for j in self.pose_joint_ids]
        )

    def _inertials_from_urdf(self):
        """beta = [m, m*c] and the inertia about the CoM per body, read from the URDF itself
        (pinocchio merges fixed links into their parent joint, which would lose the plates)."""
        beta = np.zeros(self.n_beta)
        inertias = np.zeros((self.n_bodies, 3, 3))
        for i, body in enumerate(self.body_names):
            inertial = self._urdf.find(f"link[@name='{body}']/inertial")
            m = float(inertial.find('mass').get('value'))
            c = np.array([float(v) for v in inertial.find('origin').get('xyz').split()])
            beta[4 * i : 4 * i + 4] = [m, *(m * c)]
            a = {k: float(v) for k, v in inertial.find('inertia').attrib.items()}
            inertias[i] = [
                [a['ixx'], a['ixy'], a['ixz']],
                [a['ixy'], a['iyy'], a['iyz']],
                [a['ixz'], a['iyz'], a['izz']],
            ]
        return beta, inertias

    def _wheel_geometry(self):
        """Wheel radius from the wheels' collision cylinders, track width from their joint
        origins."""
        radii = [
            float(self._urdf.find(f"link[@name='{w}']/collision/geometry/cylinder").get('radius'))
            for w in self.wheels
        ]
        xs = []
        for joint in self._urdf.findall('joint'):
            if joint.find('child').get('link') in self.wheels:
                xs.append(float(joint.find('origin').get('xyz').split()[0]))
        if len(set(radii)) != 1:
            raise ValueError(f'{self.urdf_path.name}: wheels of different radii {radii}')
        return radii[0], (max(xs) - min(xs)) if len(xs) == 2 else 0.0

    def pin_configuration(self, joints):
        """A pinocchio q (nq,) for one pose given in pose order (unbounded joints take cos/sin)."""
        q = pin.neutral(self.model)
        for jid, angle in zip(self.pose_joint_ids, np.asarray(joints, dtype=float)):
            jm = self.model.joints[jid]
            if jm.nq == 2:
                q[jm.idx_q : jm.idx_q + 2] = np.cos(angle), np.sin(angle)
            else:
                q[jm.idx_q] = angle
        return q

    def beta_labels(self):
        """'Body.quantity' for each of the 4*n_bodies beta entries."""
        return [f'{b}.{k}' for b in self.body_names for k in BETA_QUANTITIES]


def _joint_chain(model):
    n = model.njoints
    parents = np.array(model.parents, dtype=int)
    rotations = np.zeros((n, 3, 3))
    translations = np.zeros((n, 3))
    axes = np.zeros((n, 3))
    data = model.createData()
    for j in range(1, n):
        rotations[j] = model.jointPlacements[j].rotation
        translations[j] = model.jointPlacements[j].translation
        # The axis is what the joint's motion subspace says; works for RX/RY/RZ, unaligned and
        # unbounded.
        jm = model.joints[j]
        q = pin.neutral(model)
        v = np.zeros(model.nv)
        v[jm.idx_v] = 1.0
        pin.forwardKinematics(model, data, q, v)
        axes[j] = data.v[j].angular
    rotations[0] = np.eye(3)
    return JointChain(parents, rotations, translations, axes)


@lru_cache(maxsize=None)
def load_krang():
    """Golem Krang as in the paper's hardware experiments (23 bodies, 92 beta entries)."""
    return RobotModel(KRANG_URDF, KRANG_BODIES, KRANG_POSE_JOINTS, 'krang')


@lru_cache(maxsize=None)
def load_wip7():
    """The paper's planar 7-link WIP (Matlab proof of concept)."""
    bodies = tuple(f'link{i}' for i in range(1, 8)) + ('wheel',)
    joints = tuple(f'joint{i}' for i in range(2, 8))
    return RobotModel(WIP7_URDF, bodies, joints, 'wip7', wheels=('wheel',))
