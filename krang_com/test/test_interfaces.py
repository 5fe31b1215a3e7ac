"""The two ROS packages as a ROS user's workspace sees them, and the robot's own message types:
colcon and rosdep find krang_com and krang_com_interfaces (and never the test-only tf2_msgs); the
test-only TFMessage hashes as upstream Jazzy's; the mode constants are the controller's; today's
messages and older bags' forms read the same values."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import CHECKOUT
from krang_adrc_controller.detector import BalancedPoint
from krang_adrc_controller.modes import MODE_CODES
from krang_core import message_values as values
from krang_core.names import BASE_PITCH

COLCON = Path(sys.executable).parent / 'colcon'

pytest.importorskip('krang_com_interfaces', reason='built by ./dev (colcon) into the venv')
from krang_com_interfaces.msg import ControllerMode  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray, String  # noqa: E402

from krang_ros import messages  # noqa: E402

#: tf2_msgs/msg/TFMessage's type hash on ROS 2 Jazzy, as `ros2 topic info /tf --verbose` prints it
UPSTREAM_TFMESSAGE_HASH = 'RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'


def test_a_workspace_finds_both_packages_and_not_the_test_only_one(tmp_path):
    """`colcon list` in a workspace with this repository under src/ (colcon stops descending at
    a package.xml, so the two packages must sit side by side)."""
    if not COLCON.exists():
        pytest.skip('colcon is not installed in this environment (pip: colcon-common-extensions)')
    (tmp_path / 'src').mkdir()
    (tmp_path / 'src' / 'krang_com').symlink_to(CHECKOUT, target_is_directory=True)
    result = subprocess.run(
        [str(COLCON), 'list', '--names-only', '--base-paths', 'src'],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert sorted(result.stdout.split()) == ['krang_com', 'krang_com_interfaces']


def test_rosdep_finds_both_packages():
    """rosdep reads packages with catkin_pkg, which also stops at a package.xml."""
    packages = pytest.importorskip('catkin_pkg.packages')
    found = sorted(p.name for p in packages.find_packages(str(CHECKOUT)).values())
    assert found == ['krang_com', 'krang_com_interfaces']


def test_test_only_tfmessage_hashes_as_upstream():
    share = Path(sys.prefix) / 'share' / 'tf2_msgs' / 'msg' / 'TFMessage.json'
    if not share.exists():
        pytest.skip('the test-only tf2_msgs is built by ./dev')
    hashes = {
        h['type_name']: h['hash_string'] for h in json.loads(share.read_text())['type_hashes']
    }
    assert hashes['tf2_msgs/msg/TFMessage'] == UPSTREAM_TFMESSAGE_HASH


def test_mode_constants_are_the_controllers():
    assert {k: getattr(ControllerMode, k.upper()) for k in MODE_CODES} == MODE_CODES
    assert set(values.MODE_NAMES) == set(MODE_CODES)


def point(n):
    return BalancedPoint(
        t=1.0,
        q_base=-0.0123,
        joints=np.linspace(-1.0, 1.0, n),
        q_base_std=0.004,
        n_samples=45,
        window_s=1.5,
        q_base_se=0.0006,
        joints_se=np.full(n, 1e-4),
        q_base_filter=-0.0119,
    )


def test_a_balanced_pose_reads_the_same_in_both_forms():
    names = [f'J{i}' for i in range(5)]
    p = point(5)
    new = messages.balanced_pose(messages.stamp(3.0), names, p)
    old = JointState(name=names + [BASE_PITCH], position=list(p.joints) + [p.q_base])
    old.effort = list(p.joints_se) + [p.q_base_se]
    order = names[::-1]
    a, b = values.balanced_pose_values(new, order), values.balanced_pose_values(old, order)
    assert a.q_base == b.q_base == p.q_base and a.q_base_se == b.q_base_se == p.q_base_se
    np.testing.assert_array_equal(a.joints, p.joints[::-1])
    np.testing.assert_array_equal(a.joints, b.joints)
    np.testing.assert_array_equal(a.joints_se, b.joints_se)
    assert new.settle_window.sec == 1 and new.settle_window.nanosec == 500_000_000
    assert new.samples == 45 and new.base_pitch_std == 0.004
    assert values.balanced_pose_values(new, names + ['missing']) is None
    new.base_pitch = float('nan')
    assert values.balanced_pose_values(new, names) is None


def test_a_mass_model_reads_the_same_as_the_older_arrays():
    n = 8
    beta, cov = np.arange(1.0, n + 1), np.diag(np.arange(n) + 0.5)
    new = messages.mass_model(messages.stamp(1.0), ['A', 'B'], beta, cov, 'map-online', 3)
    got_beta, got_cov = values.mass_model_values(new, n)
    np.testing.assert_array_equal(got_beta, beta)
    np.testing.assert_array_equal(got_cov, cov)
    old_beta = Float64MultiArray(data=list(beta))
    assert values.mass_model_values(old_beta, n)[1] is None
    old_posterior = Float64MultiArray(data=list(np.vstack([beta, cov]).ravel()))
    np.testing.assert_array_equal(values.mass_model_values(old_posterior, n)[1], cov)
    assert values.mass_model_values(old_beta, n + 4) is None
    unknown = messages.mass_model(messages.stamp(1.0), ['A', 'B'], beta)
    assert values.mass_model_values(unknown, n)[1] is None


def test_mode_and_fault_read_the_same_as_the_older_strings():
    stamp = messages.stamp(0.0)
    for name in MODE_CODES:
        assert values.mode_name(messages.controller_mode(stamp, name)) == name
        assert values.mode_name(String(data=name)) == name
    reason = 'left drive rebooted'
    assert values.drive_fault_reason(messages.drive_fault(stamp, reason)) == reason
    assert values.drive_fault_reason(messages.drive_fault(stamp, '')) == ''
    assert values.drive_fault_reason(String(data='x')) == 'x'
