"""The report of an online session: learning curve and CoM error against the hidden true model."""
import math

import numpy as np

from krang_model.com import com_error, lateral_com_error
from krang_ros.names import BALANCED_POSE, BETA, WHEEL_EFFORT_CMD

from .reader import read_float_arrays, read_joint_states


def held_out_configurations(robot, n=2000, seed=12345):
    """Random joint configurations within the limits (rotating joints within +-pi), never used for
    learning."""
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(robot.lower, -math.pi), np.minimum(robot.upper, math.pi)
    return rng.uniform(lo, hi, (n, len(lo)))


def learning_curve(robot, betas, true_beta, n_configs=2000):
    """Forward and lateral CoM errors (m) of each beta over the held-out configurations
    (krang_model.com)."""
    joints = held_out_configurations(robot, n_configs)
    forward = np.array([com_error(robot, b, true_beta, joints) for b in betas])
    lateral = np.array([lateral_com_error(robot, b, true_beta, joints) for b in betas])
    return forward, lateral


def session_figures(bag, robot, true_beta, out_dir):
    """learning_curve.png and session_timeline.png; returns ((forward, lateral) curves, paths)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator
    betas = read_float_arrays(bag, BETA).rows
    betas = [b for b in betas if len(b) == robot.n_beta]
    curve, lateral = learning_curve(robot, betas, true_beta)
    paths = []
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(np.arange(len(curve)), 1000 * curve, 'o-',
            label='forward (x_com: what balancing observes)')
    ax.plot(np.arange(len(lateral)), 1000 * lateral, 's--', color='grey',
            label='sideways (unobservable in pitch)')
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel('balanced poses learned')
    ax.set_ylabel('mean CoM error (mm)')
    ax.set_title('Online learning against the hidden true model')
    ax.legend(fontsize=8)
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
        ax.plot(effort.t - t0, np.nansum(effort.rows, axis=1), lw=0.6,
                label='total wheel torque (N m)')
        for k, t in enumerate(poses.t):
            ax.axvline(t - t0, color='g', lw=0.8, alpha=0.6,
                       label='balanced pose learned' if k == 0 else None)
        ax.set_xlabel('time (s)')
        ax.set_ylabel('N m')
        ax.legend(loc='upper right')
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        paths.append(out_dir / 'session_timeline.png')
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)
    return (curve, lateral), paths
