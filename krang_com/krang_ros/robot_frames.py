"""The robot's coordinate frames for tf and viewers, as plain numpy (no rclpy): the core of
state_publisher and `krang view`.

The tree follows REP-105: odom -> base_footprint -> base_link, then the URDF's links.
- odom -> base_footprint: planar wheel odometry. The ground-referenced wheel angle is the encoder
  angle plus the base pitch (krang_model/README.md); travel = radius x that angle, yaw from the
  difference of the two wheels over the track width. The IMU's yaw is not used: the DMU has no
  magnetometer, so REP-145 lets it be arbitrary.
- base_footprint -> base_link: the axle midpoint, one wheel radius above the floor, with the
  IMU's orientation (yaw removed) turned from imu_link to base_link through the URDF.
- base_link -> Base: the inverse of the URDF's fixed joint Base -> base_link. The URDF is rooted at
  Base (its origin on the axle is what the model code is written in), while REP-105 needs base_link
  below base_footprint, so this one edge is published child-to-parent.
- every other URDF joint parent -> child: fixed joints once (/tf_static), moving joints from their
  positions (/tf), both from pinocchio's forward kinematics of the same URDF.

The CoM the viewers draw (com_now, com_marks) is in base_footprint: frame 0 of krang_model.com
(origin at the axle midpoint, x along the heading, z up) is base_footprint raised by one wheel
radius.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from krang_model import com
from krang_model.robot import KRANG_URDF

ODOM, BASE_FOOTPRINT, BASE_LINK, IMU_LINK = 'odom', 'base_footprint', 'base_link', 'imu_link'
WHEELS = ('JLWheel', 'JRWheel')


@dataclass(frozen=True)
class Transform:
    """Pose of `child` in `parent`: p_parent = rotation @ p_child + translation."""

    parent: str
    child: str
    translation: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3)

    @property
    def quaternion(self):
        return quaternion_from_matrix(self.rotation)


def quaternion_from_matrix(r):
    """(x, y, z, w) of a rotation matrix, w >= 0."""
    x, y, z, w = pin.Quaternion(np.asarray(r, dtype=float)).coeffs()
    sign = -1.0 if w < 0 else 1.0
    return sign * float(x), sign * float(y), sign * float(z), sign * float(w)


def matrix_from_quaternion(x, y, z, w):
    return pin.Quaternion(float(w), float(x), float(y), float(z)).normalized().matrix()


def _rot_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class WheelOdometry:
    """Planar pose (x, y, yaw) of base_footprint in odom from the wheel encoders and the pitch."""

    def __init__(self, radius, track):
        self.radius, self.track = float(radius), float(track)
        self.x = self.y = self.yaw = 0.0
        self._last = None

    def update(self, left, right, pitch):
        """Encoder angles (positive rolls forward) and the base pitch (rad) -> (x, y, yaw)."""
        ground = np.array([left, right], dtype=float) + float(pitch)
        if self._last is not None:
            d_left, d_right = self.radius * (ground - self._last)
            ds = 0.5 * (d_left + d_right)
            d_yaw = (d_right - d_left) / self.track
            mid = self.yaw + 0.5 * d_yaw
            self.x += ds * math.cos(mid)
            self.y += ds * math.sin(mid)
            self.yaw += d_yaw
        self._last = ground
        return self.x, self.y, self.yaw


class RobotFrames:
    """The URDF's transforms and the base's place in the world (see the module docstring)."""

    def __init__(self, urdf_path=KRANG_URDF):
        self.urdf_text = Path(urdf_path).read_text()
        self.model = pin.buildModelFromXML(self.urdf_text)
        self.data = self.model.createData()
        root = ET.fromstring(self.urdf_text)
        self.joints = [
            (
                j.get('name'),
                j.get('type'),
                j.find('parent').get('link'),
                j.find('child').get('link'),
            )
            for j in root.findall('joint')
        ]
        self.links = [link.get('name') for link in root.findall('link')]
        self._frame = {
            name: self.model.getFrameId(name, pin.FrameType.BODY) for name in self.links
        }
        self._joint_id = {self.model.names[j]: j for j in range(1, self.model.njoints)}
        self.q = pin.neutral(self.model)
        pin.framesForwardKinematics(self.model, self.data, self.q)
        self._static = [
            self._relative(parent, child)
            for _, kind, parent, child in self.joints
            if kind == 'fixed'
        ]
        imu_in_base_link = self._relative(BASE_LINK, IMU_LINK)
        self._base_link_in_imu = imu_in_base_link.rotation.T
        self.radius, self.track = self._wheel_geometry(root)
        self.odometry = WheelOdometry(self.radius, self.track)

    @staticmethod
    def _wheel_geometry(root):
        """Wheel radius (collision cylinder), track (joint origins): as krang_model reads them."""
        joints = {j.get('name'): j for j in root.findall('joint')}
        links = [joints[w].find('child').get('link') for w in WHEELS]
        radius = float(
            root.find(f"link[@name='{links[0]}']/collision/geometry/cylinder").get('radius')
        )
        xs = [float(joints[w].find('origin').get('xyz').split()[0]) for w in WHEELS]
        return radius, abs(xs[1] - xs[0])

    def _relative(self, parent, child):
        a = self.data.oMf[self._frame[parent]]
        b = self.data.oMf[self._frame[child]]
        rel = a.actInv(b)
        return Transform(parent, child, rel.translation.copy(), rel.rotation.copy())

    def static_transforms(self):
        """Fixed URDF joints, base_link -> Base inverted so that base_link is the tree's root."""
        out = []
        for t in self._static:
            if t.child == BASE_LINK:
                out.append(
                    Transform(BASE_LINK, t.parent, -t.rotation.T @ t.translation, t.rotation.T)
                )
            else:
                out.append(t)
        return out

    def set_joints(self, positions):
        """Joint positions by URDF name (others keep their last value); unknown names ignored."""
        for name, angle in positions.items():
            j = self._joint_id.get(name)
            if j is None or not math.isfinite(angle):
                continue
            jm = self.model.joints[j]
            if jm.nq == 2:  # continuous joint: (cos, sin)
                self.q[jm.idx_q : jm.idx_q + 2] = math.cos(angle), math.sin(angle)
            else:
                self.q[jm.idx_q] = angle
        pin.framesForwardKinematics(self.model, self.data, self.q)

    def joint_transforms(self, names=None):
        """parent -> child of the moving URDF joints (all, or those in `names`), at set_joints."""
        return [
            self._relative(parent, child)
            for name, kind, parent, child in self.joints
            if kind != 'fixed' and (names is None or name in names)
        ]

    def base_link_in_footprint(self, imu_quaternion):
        """base_footprint -> base_link from the IMU orientation (x, y, z, w) of imu_link in a
        gravity-aligned frame; also returns the pitch of base_link about its y axis (the axle).

        The heading removed is that of the axle, so it is defined at any pitch (an Euler-angle
        yaw flips by pi once the pitch passes -90 deg, as it does sitting on the caster)."""
        r = matrix_from_quaternion(*imu_quaternion) @ self._base_link_in_imu
        yaw = math.atan2(-r[0, 1], r[1, 1])
        r = _rot_z(-yaw) @ r
        pitch = math.atan2(-r[2, 0], r[0, 0])
        return Transform(BASE_FOOTPRINT, BASE_LINK, np.array([0.0, 0.0, self.radius]), r), pitch

    def base_transforms(self, imu_quaternion, left_wheel, right_wheel):
        """[odom -> base_footprint, base_footprint -> base_link] from the IMU and the wheels."""
        base, pitch = self.base_link_in_footprint(imu_quaternion)
        x, y, yaw = self.odometry.update(left_wheel, right_wheel, pitch)
        odom = Transform(ODOM, BASE_FOOTPRINT, np.array([x, y, 0.0]), _rot_z(yaw))
        return [odom, base]


def com_now(robot, frames, imu_quaternion, joints, beta):
    """(q_base, CoM of `beta`, CoM of the URDF's nominal beta), both in frame 0, at the pitch of
    the IMU orientation (x, y, z, w) and the body joints `joints` (pose order)."""
    _, q_base = frames.base_link_in_footprint(imu_quaternion)
    # one pass of the kinematics for both betas (com.com_frame0 for each would take two): the
    # mass moment over the total mass
    moment = com.regressor(robot, q_base, np.asarray(joints, dtype=float)[None])[0]
    estimated, nominal = (
        moment @ b / b[0::4].sum() for b in (np.asarray(beta, float), robot.nominal_beta)
    )
    return q_base, estimated, nominal


@dataclass(frozen=True)
class ComMarks:
    """What a viewer draws of the CoM, in base_footprint: a vertical line from the axle to `top`
    (balanced: the CoM is on it), a line from the axle to the estimated CoM, the estimated CoM
    (red) and the nominal one (grey), and a label."""

    axle: np.ndarray
    top: np.ndarray
    estimated: np.ndarray
    nominal: np.ndarray
    label: str


def com_marks(q_base, estimated, nominal, radius, mode=''):
    """ComMarks of com_now's CoMs (frame 0) for a wheel of `radius`; `mode` goes in the label."""
    axle = np.array([0.0, 0.0, float(radius)])
    est, nom = np.asarray(estimated, float) + axle, np.asarray(nominal, float) + axle
    label = (
        f'CoM {1000 * estimated[0]:+.1f} mm ahead of the axle (estimated beta, red); '
        f'nominal {1000 * nominal[0]:+.1f} mm (grey); q_base {q_base:+.3f} rad'
    )
    return ComMarks(
        axle=axle,
        top=np.array([0.0, 0.0, max(est[2], nom[2]) + 0.3]),
        estimated=est,
        nominal=nom,
        label=label + (f'; mode {mode}' if mode else ''),
    )
