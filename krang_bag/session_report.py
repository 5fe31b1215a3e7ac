"""The report of an online session: learning curve and CoM error against the hidden true model."""
import math

import numpy as np

from krang_model.com import balance_pitch, com_frame0
from krang_ros.names import BALANCED_POSE, BETA, WHEEL_EFFORT_CMD

from .reader import read_float_arrays, read_joint_states


def held_out_configurations(robot, n=2000, seed=12345):
    """Random joint configurations within the limits (rotating joints within +-pi), never used for learning."""
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(robot.lower, -math.pi), np.minimum(robot.upper, math.pi)
    return rng.uniform(lo, hi, (n, len(lo)))


def com_error(robot, beta, true_beta, joints):
    """Mean horizontal distance (m) between the CoM beta predicts and the true CoM, at each configuration
    held at the pitch where the true robot balances."""
    q_base = balance_pitch(robot, joints, true_beta)
    est = com_frame0(robot, q_base, joints, beta)
    true = com_frame0(robot, q_base, joints, true_beta)
    return float(np.mean(np.hypot(est[:, 0] - true[:, 0], est[:, 1] - true[:, 1])))


def learning_curve(robot, betas, true_beta, n_configs=2000):
    joints = held_out_configurations(robot, n_configs)
    return np.array([com_error(robot, b, true_beta, joints) for b in betas])


def session_figures(bag, robot, true_beta, out_dir):
    """learning_curve.png and session_timeline.png; returns (curve, paths)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    betas = read_float_arrays(bag, BETA).rows
    betas = [b for b in betas if len(b) == robot.n_beta]
    curve = learning_curve(robot, betas, true_beta)
    paths = []
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(np.arange(len(curve)), 1000 * curve, 'o-')
    ax.set_xlabel('balanced poses learned')
    ax.set_ylabel('mean horizontal CoM error (mm)')
    ax.set_title('Online learning against the hidden true model')
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    paths.append(out_dir / 'learning_curve.png')
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    effort = read_float_arrays(bag, WHEEL_EFFORT_CMD)
    poses = read_joint_states(bag, BALANCED_POSE)
    if len(effort.t):
        t0 = effort.t[0]
        fig, ax = plt.subplots(figsize=(8, 3.5))
        ax.plot(effort.t - t0, np.nansum(effort.rows, axis=1), lw=0.6, label='total wheel torque (N m)')
        for k, t in enumerate(poses.t):
            ax.axvline(t - t0, color='g', lw=0.8, alpha=0.6, label='balanced pose learned' if k == 0 else None)
        ax.set_xlabel('time (s)')
        ax.set_ylabel('N m')
        ax.legend(loc='upper right')
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        paths.append(out_dir / 'session_timeline.png')
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)
    return curve, paths
