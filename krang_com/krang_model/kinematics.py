"""Batched forward kinematics: body frames in the base frame for many poses at once.

pinocchio evaluates one configuration per call (tens of microseconds from Python); the pose pool
and the pose filter need phi at 10^5 poses, so the same joint chain (placements and axes read from
pinocchio) is evaluated here with stacked numpy rotations. Tests check it against pinocchio.
"""

import numpy as np


def axis_rotations(axis, angles):
    """Rodrigues: rotation matrices (N, 3, 3) about a unit axis."""
    angles = np.asarray(angles, dtype=float)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    k2 = k @ k
    s = np.sin(angles)[:, None, None]
    c = (1.0 - np.cos(angles))[:, None, None]
    return np.eye(3) + s * k + c * k2


def joint_placements(robot, joints):
    """World (base-frame) rotation (N, nj, 3, 3) and translation (N, nj, 3) of every joint
    frame."""
    joints = np.atleast_2d(np.asarray(joints, dtype=float))
    n = joints.shape[0]
    chain = robot.chain
    nj = len(chain.parents)
    q_full = np.zeros((n, nj))
    q_full[:, robot.pose_joint_ids] = joints
    rot = np.empty((n, nj, 3, 3))
    trans = np.empty((n, nj, 3))
    rot[:, 0] = np.eye(3)
    trans[:, 0] = 0.0
    for j in range(1, nj):
        p = chain.parents[j]
        r_parent = rot[:, p]
        r_fixed = r_parent @ chain.rotations[j]  # (N,3,3)
        trans[:, j] = trans[:, p] + r_parent @ chain.translations[j]
        if np.any(q_full[:, j]):
            rot[:, j] = r_fixed @ axis_rotations(chain.axes[j], q_full[:, j])
        else:
            rot[:, j] = r_fixed
    return rot, trans


def body_placements(robot, joints):
    """Rotation (N, B, 3, 3) and translation (N, B, 3) of each beta body frame in the base
    frame."""
    rot_j, trans_j = joint_placements(robot, joints)
    n = rot_j.shape[0]
    rot = np.empty((n, robot.n_bodies, 3, 3))
    trans = np.empty((n, robot.n_bodies, 3))
    for b, frame in enumerate(robot.body_frames):
        r_parent = rot_j[:, frame.parentJoint]
        rot[:, b] = r_parent @ frame.placement.rotation
        trans[:, b] = trans_j[:, frame.parentJoint] + r_parent @ frame.placement.translation
    return rot, trans


def rotate_rows_by_axis(rows, axis, angles):
    """rows @ Rot(axis, angle) for row vectors rows (N, 3): Rodrigues on vectors, no matrices."""
    c = np.cos(angles)[:, None]
    s = np.sin(angles)[:, None]
    axis = np.asarray(axis, dtype=float)
    # v^T R(a, q) = (R(a, -q) v)^T = v cos q - (a x v) sin q + a (a . v)(1 - cos q), with the
    # cross and outer products as 3x3 products of the rows: (a x v)^T = v^T [a]x^T, a (a . v) =
    # (v^T a a^T)^T
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return rows * c - (rows @ skew.T) * s + (rows @ np.outer(axis, axis)) * (1.0 - c)


def projected_body_placements(robot, joints, direction):
    """For each body: d . p_b (N, B) and d^T R_b (N, B, 3), with one base-frame row vector d (N, 3)
    per pose. This is all phi needs, and costs vector operations instead of 3x3 products."""
    joints = np.atleast_2d(np.asarray(joints, dtype=float))
    chain = robot.chain
    nj = len(chain.parents)
    n = joints.shape[0]
    q_full = np.zeros((n, nj))
    q_full[:, robot.pose_joint_ids] = joints
    row = np.empty((nj, n, 3))  # d^T R_j
    offset = np.empty((nj, n))  # d . p_j
    row[0] = direction
    offset[0] = 0.0
    for j in range(1, nj):
        p = chain.parents[j]
        offset[j] = offset[p] + row[p] @ chain.translations[j]
        fixed = row[p] @ chain.rotations[j]
        row[j] = (
            rotate_rows_by_axis(fixed, chain.axes[j], q_full[:, j])
            if np.any(q_full[:, j])
            else fixed
        )
    body_offset = np.empty((n, robot.n_bodies))
    body_row = np.empty((n, robot.n_bodies, 3))
    for b, frame in enumerate(robot.body_frames):
        pj = frame.parentJoint
        body_offset[:, b] = offset[pj] + row[pj] @ frame.placement.translation
        body_row[:, b] = row[pj] @ frame.placement.rotation
    return body_offset, body_row
