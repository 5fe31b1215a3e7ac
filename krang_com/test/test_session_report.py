"""The session figures: every mark of the timeline is in its legend, modes are bands, pose moves
and learned poses are lines, and the figures are written (atomically) as PNGs; from bags of
today's types and of the older forms (krang_core.message_values) alike."""

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from std_msgs.msg import Float64MultiArray

from krang_bag.reader import read_float_arrays
from krang_bag.session_report import mode_segments, read_modes, session_figures, timeline_figure
from krang_adrc_controller.detector import BalancedPoint
from krang_bag.writer import BagWriter
from krang_model.robot import load_krang
from krang_core import names
from krang_ros import messages

MODES = [
    (0.0, 'sit'),
    (1.0, 'sit'),
    (2.0, 'stand_up'),
    (3.0, 'balance'),
    (4.0, 'balance'),
    (8.0, 'sit_down'),
    (9.0, 'sit'),
]
TARGETS = [3.5, 5.5]
LEARNED = [5.0, 7.0]


def test_mode_segments_merge_repeated_reports():
    times, modes = zip(*MODES)
    assert mode_segments(np.array(times), list(modes), 10.0) == [
        (0.0, 2.0, 'sit'),
        (2.0, 3.0, 'stand_up'),
        (3.0, 8.0, 'balance'),
        (8.0, 9.0, 'sit_down'),
        (9.0, 10.0, 'sit'),
    ]
    assert mode_segments(np.array([]), [], 10.0) == []


@pytest.fixture(params=['today', 'older'])
def bag(tmp_path, request):
    return write_session(tmp_path / 'session.mcap', forms=request.param)


def learned_pose(robot, forms):
    """A /balanced_pose message: a BalancedPose, or an older bag's JointState."""
    n = len(robot.pose_joints)
    if forms == 'today':
        point = BalancedPoint(0.0, 0.0, np.zeros(n), q_base_std=0.0, n_samples=100, window_s=2.0)
        return messages.balanced_pose(Time(), robot.pose_joints, point)
    return messages.joint_state(
        Time(), list(robot.pose_joints) + [names.BASE_PITCH], np.zeros(n + 1)
    )


def published_beta(robot, beta, forms):
    """A /com_estimator/beta message: MassModel, or an older bag's labelled Float64MultiArray."""
    if forms == 'today':
        return messages.mass_model(Time(), robot.body_names, beta, source='map-online')
    return messages.labelled_array(beta, robot.beta_labels())


def write_session(path, betas=3, forms='today'):
    """A session bag: wheel efforts, diagnostics, targets, learned poses and `betas` betas, the
    learning topics in today's types or in the older `forms`."""
    robot = load_krang()
    s = 10**9
    today = forms == 'today'
    with BagWriter(path) as w:
        w.add_topic(names.WHEEL_EFFORT_CMD, 'std_msgs/msg/Float64MultiArray')
        w.add_topic(names.DIAGNOSTICS, 'diagnostic_msgs/msg/DiagnosticArray')
        w.add_topic(names.POSE_TARGET, 'sensor_msgs/msg/JointState')
        w.add_topic(
            names.BALANCED_POSE,
            'krang_com_interfaces/msg/BalancedPose' if today else 'sensor_msgs/msg/JointState',
        )
        w.add_topic(
            names.BETA,
            'krang_com_interfaces/msg/MassModel' if today else 'std_msgs/msg/Float64MultiArray',
        )
        for k in range(101):
            w.write_message(
                names.WHEEL_EFFORT_CMD, Float64MultiArray(data=[0.1 * k, 0.0]), s + k * s // 10
            )
        for t, mode in MODES:
            w.write_message(
                names.DIAGNOSTICS,
                messages.diagnostics(Time(), 'adrc_controller', 'ok', '', {'mode': mode}),
                s + int(t * s),
            )
            w.write_message(
                names.DIAGNOSTICS,
                messages.diagnostics(Time(), 'com_estimator', 'ok', '', {'poses': 0}),
                s + int(t * s),
            )
        for t in TARGETS:
            w.write_message(
                names.POSE_TARGET,
                messages.joint_state(Time(), robot.pose_joints, np.zeros(len(robot.pose_joints))),
                s + int(t * s),
            )
        for t in LEARNED:
            w.write_message(names.BALANCED_POSE, learned_pose(robot, forms), s + int(t * s))
        for k in range(betas):
            beta = robot.nominal_beta * (1 + 0.01 * k)
            w.write_message(names.BETA, published_beta(robot, beta, forms), s + k * s)
    return path


def test_timeline_marks_and_legend(bag):
    times, modes = read_modes(bag)
    assert modes == [m for _, m in MODES]  # only the controller's reports
    fig = timeline_figure(bag, read_float_arrays(bag, names.WHEEL_EFFORT_CMD))
    ax = fig.axes[0]
    assert ax.get_title() == 'Session timeline: session.mcap'
    labels = ax.get_legend_handles_labels()[1]
    assert labels == [
        'controller mode: sit',
        'controller mode: stand_up',
        'controller mode: balance',
        'controller mode: sit_down',
        'total wheel torque command (N m)',
        'pose move starts (new /pose_server/target)',
        'balanced pose detected and learned',
    ]
    assert len(ax.patches) == 5  # one band per mode segment
    vertical = sorted(line.get_xdata()[0] for line in ax.lines[1:])
    assert vertical == pytest.approx(sorted(TARGETS + LEARNED))
    # every drawn mark has a legend entry (unlabelled repeats share their first's style)
    styles = {(line.get_color(), line.get_linestyle()) for line in ax.lines}
    assert len(styles) == 3


def test_session_figures_written(bag, tmp_path):
    robot = load_krang()
    (curve, lateral), paths = session_figures(bag, robot, robot.nominal_beta, tmp_path, None)
    assert [p.name for p in paths] == ['learning_curve.png', 'session_timeline.png']
    assert all(p.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' for p in paths)
    assert len(curve) == 3 and curve[0] == pytest.approx(0.0, abs=1e-12)
    assert not list(tmp_path.glob('.*.tmp'))


def test_a_session_stopped_before_any_beta_still_has_its_curve(tmp_path):
    """Ctrl-C during stand-up: the estimator never published; the curve is the initial beta's."""
    robot = load_krang()
    bag = write_session(tmp_path / 'early.mcap', betas=0)
    beta0 = robot.nominal_beta.copy()
    beta0[4 * robot.body_names.index('Base') + 2] += 0.5  # the Base's CoM 6.6 mm off
    (curve, lateral), paths = session_figures(bag, robot, robot.nominal_beta, tmp_path, beta0)
    assert len(curve) == 1 and curve[0] > 1e-4  # beta0's error, not the truth's zero
    assert [p.name for p in paths] == ['learning_curve.png', 'session_timeline.png']
