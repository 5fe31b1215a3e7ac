"""The live Foxglove view of `krang view`, without ROS: what the robot's measurements become on a
Foxglove WebSocket server (foxglove-sdk). The ROS shell (krang_ros.view_node) only feeds it.

Channels (Foxglove topics):
  /transforms   foxglove.FrameTransforms: the tf tree of krang_ros.robot_frames (odom ->
                base_footprint -> base_link -> Base -> every link), from the joints and the IMU
  /robot        foxglove.SceneUpdate: the URDF's collision boxes and cylinders, an entity per link,
                locked to its frame (re-sent every second for clients that join later)
  /com          foxglove.SceneUpdate in base_footprint: the CoM of the estimated beta (red) and of
                the URDF's nominal beta (grey) over the axle (green vertical line), with a label
  /com_live     JSON {q_base_rad, x_com_mm, x_com_nominal_mm}: the estimated CoM's horizontal
                offset ahead of the axle now, at the measured pitch and joints
  /learning     JSON {pose, x_com_mm, beta_step}: one sample per learned balanced pose (the
                estimator's CoM offset at that pose's measured pitch with the new beta, and the
                size of the beta update), the learning curve
  /mode         JSON {mode}: the controller's mode
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET

import foxglove
import numpy as np
import pinocchio as pin
from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel
from foxglove.messages import (
    Color,
    CubePrimitive,
    CylinderPrimitive,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Vector3,
)

from krang_model.robot import load_krang
from krang_ros.robot_frames import (
    BASE_FOOTPRINT,
    WHEELS,
    RobotFrames,
    com_marks,
    com_now,
    quaternion_from_matrix,
)

COLORS = {
    'Base': (0.55, 0.55, 0.6),
    'LWheel': (0.15, 0.15, 0.15),
    'RWheel': (0.15, 0.15, 0.15),
    'Spine': (0.45, 0.5, 0.6),
    'Bracket': (0.45, 0.5, 0.6),
}
ARM_COLOR = (0.35, 0.55, 0.8)
JSON_SCHEMAS = {
    '/com_live': {'q_base_rad': 'number', 'x_com_mm': 'number', 'x_com_nominal_mm': 'number'},
    '/learning': {'pose': 'integer', 'x_com_mm': 'number', 'beta_step': ['number', 'null']},
    '/mode': {'mode': 'string'},
}


def _vec(v):
    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _point(p):
    return Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _quat(q):
    return Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])


def _pose(xyz, rotation=np.eye(3)):
    return Pose(position=_vec(xyz), orientation=_quat(quaternion_from_matrix(rotation)))


def _color(rgb, a=1.0):
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


def robot_scene(frames):
    """One entity per URDF link with its collision geometry (the URDF has no visuals)."""
    entities = []
    for link in ET.fromstring(frames.urdf_text).findall('link'):
        name = link.get('name')
        rgb = COLORS.get(name, ARM_COLOR)
        cubes, cylinders = [], []
        for col in link.findall('collision'):
            origin = col.find('origin')
            xyz = [float(v) for v in origin.get('xyz', '0 0 0').split()]
            rpy = [float(v) for v in origin.get('rpy', '0 0 0').split()]
            pose = _pose(xyz, pin.rpy.rpyToMatrix(*rpy))
            box, cyl = col.find('geometry/box'), col.find('geometry/cylinder')
            if box is not None:
                size = [float(v) for v in box.get('size').split()]
                cubes.append(CubePrimitive(pose=pose, size=_vec(size), color=_color(rgb, 0.8)))
            elif cyl is not None:
                d, length = 2 * float(cyl.get('radius')), float(cyl.get('length'))
                cylinders.append(
                    CylinderPrimitive(
                        pose=pose,
                        size=Vector3(x=d, y=d, z=length),
                        bottom_scale=1.0,
                        top_scale=1.0,
                        color=_color(rgb, 0.9),
                    )
                )
        if cubes or cylinders:
            entities.append(
                SceneEntity(
                    frame_id=name, id=name, frame_locked=True, cubes=cubes, cylinders=cylinders
                )
            )
    return SceneUpdate(entities=entities)


class LiveView:
    """Robot state in, Foxglove channels out. `start` opens the WebSocket server."""

    def __init__(self):
        self.robot = load_krang()
        self.frames = RobotFrames()
        self.scene = robot_scene(self.frames)
        self.joints = {}
        self.imu_orientation = None
        self.beta = self.robot.nominal_beta.copy()
        self.beta_seen = False
        self.beta_step = None  # no update yet (JSON has no NaN)
        self.poses_learned = 0
        self.mode = ''
        self.server = None

    # ---- inputs ------------------------------------------------------------------------------
    def on_joints(self, positions):
        self.joints.update({k: float(v) for k, v in positions.items() if math.isfinite(v)})

    def on_imu(self, quaternion):
        self.imu_orientation = tuple(float(v) for v in quaternion)

    def on_beta(self, beta):
        """A new estimate; the first one (the estimator's initial beta) is no step."""
        beta = np.array(beta, dtype=float)
        if self.beta_seen:
            self.beta_step = float(np.linalg.norm(beta - self.beta))
        self.beta, self.beta_seen = beta, True

    def on_learned_com(self, point):
        """/com_estimator/com: the estimator's CoM at a newly learned balanced pose, in
        base_footprint (x: its offset ahead of the axle)."""
        self.poses_learned += 1
        sample = {
            'pose': self.poses_learned,
            'x_com_mm': 1000.0 * float(point[0]),
            'beta_step': self.beta_step,
        }
        if self.server is not None:
            self.channels['/learning'].log(sample)
        return sample

    def on_mode(self, mode):
        if mode != self.mode:
            self.mode = mode
            self.publish_mode()

    # ---- outputs -----------------------------------------------------------------------------
    def pose_joints(self):
        if any(j not in self.joints for j in self.robot.pose_joints):
            return None
        return np.array([self.joints[j] for j in self.robot.pose_joints])

    def transforms(self):
        """The whole tf tree now (None until joints, wheels and the IMU have been seen)."""
        if self.imu_orientation is None or any(w not in self.joints for w in WHEELS):
            return None
        self.frames.set_joints(self.joints)
        return (
            self.frames.static_transforms()
            + self.frames.joint_transforms()
            + self.frames.base_transforms(self.imu_orientation, *(self.joints[w] for w in WHEELS))
        )

    def com_now(self):
        """(q_base, CoM of the estimated beta, CoM of the nominal beta), frame 0, or None."""
        joints = self.pose_joints()
        if joints is None or self.imu_orientation is None:
            return None
        return com_now(self.robot, self.frames, self.imu_orientation, joints, self.beta)

    def com_scene(self, q_base, estimated, nominal):
        marks = com_marks(q_base, estimated, nominal, self.frames.radius, self.mode or '?')
        lines = [
            LinePrimitive(
                type=LinePrimitiveLineType.LineStrip,
                thickness=thickness,
                points=[_point(marks.axle), _point(end)],
                color=_color(rgb),
            )
            for end, thickness, rgb in (
                (marks.top, 0.01, (0.1, 0.8, 0.2)),
                (marks.estimated, 0.008, (0.9, 0.15, 0.1)),
            )
        ]
        spheres = [
            SpherePrimitive(
                pose=_pose(marks.estimated),
                size=Vector3(x=0.07, y=0.07, z=0.07),
                color=_color((0.9, 0.15, 0.1)),
            ),
            SpherePrimitive(
                pose=_pose(marks.nominal),
                size=Vector3(x=0.05, y=0.05, z=0.05),
                color=_color((0.6, 0.6, 0.6), 0.7),
            ),
        ]
        texts = [
            TextPrimitive(
                pose=_pose(marks.estimated + np.array([0.0, 0.0, 0.12])),
                billboard=True,
                font_size=14.0,
                scale_invariant=True,
                color=_color((1.0, 1.0, 1.0)),
                text=marks.label,
            )
        ]
        return SceneUpdate(
            entities=[
                SceneEntity(
                    frame_id=BASE_FOOTPRINT, id='com', lines=lines, spheres=spheres, texts=texts
                )
            ]
        )

    def start(self, port, host='127.0.0.1'):
        """Open the WebSocket server on host:port (0: any free port); returns the port."""
        self.context = foxglove.Context()
        ctx = self.context
        self.channels = {
            '/transforms': FrameTransformsChannel('/transforms', context=ctx),
            '/robot': SceneUpdateChannel('/robot', context=ctx),
            '/com': SceneUpdateChannel('/com', context=ctx),
        }
        for topic, fields in JSON_SCHEMAS.items():
            schema = {'type': 'object', 'properties': {k: {'type': t} for k, t in fields.items()}}
            self.channels[topic] = foxglove.Channel(
                topic,
                schema=foxglove.Schema(
                    name='krang' + topic.replace('/', '.'),
                    encoding='jsonschema',
                    data=json.dumps(schema).encode(),
                ),
                message_encoding='json',
                context=ctx,
            )
        self.server = foxglove.start_server(name='krang', host=host, port=port, context=ctx)
        return self.server.port

    def stop(self):
        if self.server is not None:
            self.server.stop()
            self.server = None

    def publish_scene(self):
        self.channels['/robot'].log(self.scene)
        self.publish_mode()

    def publish_mode(self):
        if self.server is not None and self.mode:
            self.channels['/mode'].log({'mode': self.mode})

    def publish(self):
        """The transforms, the CoM marker and the live CoM offset, as they are now."""
        transforms = self.transforms()
        if transforms is not None:
            self.channels['/transforms'].log(
                FrameTransforms(
                    transforms=[
                        FrameTransform(
                            parent_frame_id=t.parent,
                            child_frame_id=t.child,
                            translation=_vec(t.translation),
                            rotation=_quat(t.quaternion),
                        )
                        for t in transforms
                    ]
                )
            )
        now = self.com_now()
        if now is not None:
            q_base, estimated, nominal = now
            self.channels['/com'].log(self.com_scene(q_base, estimated, nominal))
            self.channels['/com_live'].log(
                {
                    'q_base_rad': q_base,
                    'x_com_mm': 1000.0 * float(estimated[0]),
                    'x_com_nominal_mm': 1000.0 * float(nominal[0]),
                }
            )
