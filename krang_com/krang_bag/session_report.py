"""The report of an online session: learning curve and CoM error against the hidden true model,
and the session timeline (torque, controller modes, pose moves, learned poses)."""

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from krang_model.com import com_error, lateral_com_error
from krang_model.files import save_figure
from krang_core.names import BALANCED_POSE, DIAGNOSTICS, POSE_TARGET, WHEEL_EFFORT_CMD

from .reader import iter_messages, read_float_arrays
from .relearn import recorded_betas


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


MODE_COLORS = {
    'sit': '#bdbdbd',
    'stand_up': '#f4a261',
    'balance': '#a8dadc',
    'sit_down': '#cdb4db',
    'safe_stop': '#e63946',
}
CONTROLLER = 'adrc_controller'  # the /diagnostics status that reports the controller's mode


def read_modes(bag):
    """(times_s, modes) of the controller's /diagnostics reports (its 'mode' value), in order."""
    times, modes = [], []
    for _, t_ns, msg in iter_messages(bag, [DIAGNOSTICS]):
        for status in msg.status:
            if status.name.endswith(CONTROLLER):
                mode = next((kv.value for kv in status.values if kv.key == 'mode'), None)
                if mode is not None:
                    times.append(t_ns * 1e-9)
                    modes.append(mode)
    return np.array(times), modes


def mode_segments(times, modes, t_end):
    """[(start, end, mode)]: each report holds until the next report of a different mode."""
    segments = []
    for t, mode in zip(times, modes):
        if segments and segments[-1][2] == mode:
            continue
        if segments:
            segments[-1][1] = t
        segments.append([t, t_end, mode])
    return [tuple(s) for s in segments if s[1] > s[0]]


def message_times(bag, topic):
    return np.array([t_ns * 1e-9 for _, t_ns, _ in iter_messages(bag, [topic])])


def session_figures(bag, robot, true_beta, out_dir, beta0):
    """learning_curve.png and session_timeline.png; returns ((forward, lateral) curves, paths).

    `beta0` is the estimator's initial beta: the curve starts from it when the session stopped
    before the estimator published one (a Ctrl-C during stand-up still gets its report)."""
    betas = list(recorded_betas(bag, robot)) or [np.asarray(beta0, float)]
    curve, lateral = learning_curve(robot, betas, true_beta)
    paths = []
    fig = Figure(figsize=(6, 3.5))
    ax = fig.add_subplot()
    ax.plot(
        np.arange(len(curve)), 1000 * curve, 'o-', label='forward (x_com: what balancing observes)'
    )
    ax.plot(
        np.arange(len(lateral)),
        1000 * lateral,
        's--',
        color='grey',
        label='sideways (unobservable in pitch)',
    )
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel('balanced poses learned (0: the initial beta)')
    ax.set_ylabel('mean CoM error (mm)')
    ax.set_title('Online learning against the hidden true model')
    ax.legend(
        fontsize=8, title='CoM error of each beta over 2000 held-out poses', title_fontsize=8
    )
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    paths.append(save_figure(fig, out_dir / 'learning_curve.png', dpi=120))

    effort = read_float_arrays(bag, WHEEL_EFFORT_CMD)
    if len(effort.t):
        paths.append(
            save_figure(timeline_figure(bag, effort), out_dir / 'session_timeline.png', dpi=120)
        )
    return (curve, lateral), paths


def timeline_figure(bag, effort):
    """Wheel torque over the session, the controller's modes as bands, the pose moves and the
    learned balanced poses as lines; the legend names every mark."""
    t0 = effort.t[0]
    t_end = effort.t[-1] - t0
    fig = Figure(figsize=(9, 4.2))
    ax = fig.add_subplot()
    times, modes = read_modes(bag)
    seen = set()
    for start, end, mode in mode_segments(times - t0, modes, t_end):
        ax.axvspan(
            max(start, 0.0),
            end,
            color=MODE_COLORS.get(mode, '#ffe08a'),
            alpha=0.45,
            lw=0,
            label=None if mode in seen else f'controller mode: {mode}',
        )
        seen.add(mode)
    ax.plot(
        effort.t - t0,
        np.nansum(effort.rows, axis=1),
        color='k',
        lw=0.6,
        label='total wheel torque command (N m)',
    )
    for k, t in enumerate(message_times(bag, POSE_TARGET) - t0):
        ax.axvline(
            t,
            color='tab:blue',
            ls='--',
            lw=0.9,
            label='pose move starts (new /pose_server/target)' if k == 0 else None,
        )
    points = [
        (t_ns * 1e-9 - t0, bool(getattr(msg, 'in_motion', False)))
        for _, t_ns, msg in iter_messages(bag, [BALANCED_POSE])
    ]
    for k, t in enumerate(t for t, moving in points if not moving):
        ax.axvline(
            t,
            color='tab:green',
            lw=1.2,
            label='balanced pose detected and learned' if k == 0 else None,
        )
    for k, t in enumerate(t for t, moving in points if moving):
        ax.axvline(
            t,
            color='tab:green',
            ls=':',
            lw=0.9,
            label='point read while moving (learned with the next pose)' if k == 0 else None,
        )
    ax.set_xlim(0.0, t_end)
    ax.set_xlabel('time since the first wheel command (s)')
    ax.set_ylabel('wheel torque (N m)')
    ax.set_title(f'Session timeline: {Path(bag).name}')
    ax.grid(True, alpha=0.3)
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=8, borderaxespad=0.0)
    fig.tight_layout()
    return fig
