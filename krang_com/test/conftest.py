"""Shared fixtures: the real robot data (skipped when absent) and ROS isolation per test run."""

import itertools
import os
import random
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]  # the krang_com package
CHECKOUT = REPO.parent  # the repository: krang_com/, krang_com_interfaces/, bench/, docs/

# Single-threaded OpenBLAS before numpy is imported, as every node and `krang` run
# (krang_ros/entry.py).
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
# DDS stays on localhost, and every test module of a run gets a domain of its own
# (ros_domain_per_module), so parallel runs never cross-talk and no module's nodes meet the ones
# an earlier module left behind or is still stopping. A ROS_DOMAIN_ID set by the user is kept.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
_USER_DOMAIN = 'ROS_DOMAIN_ID' in os.environ
_FIRST_DOMAIN = random.Random(os.getpid()).randrange(100)
_domains = itertools.count()
os.environ.setdefault('ROS_DOMAIN_ID', str(1 + _FIRST_DOMAIN))


def next_ros_domain():
    """Move this process (and what it starts from now on) to the next of the domains 1-100."""
    if not _USER_DOMAIN:
        os.environ['ROS_DOMAIN_ID'] = str(1 + (_FIRST_DOMAIN + next(_domains)) % 100)


@pytest.fixture(scope='module', autouse=True)
def ros_domain_per_module():
    """The next of the domains 1-100 for this module (its nodes and its own contexts)."""
    next_ros_domain()
    yield


def krang_data_dir():
    """The real-data kit: $KRANG_DATA, else ../shared/krang_data next to the checkout."""
    env = os.environ.get('KRANG_DATA')
    path = Path(env) if env else CHECKOUT.parent / 'shared' / 'krang_data'
    return path if (path / 'hardware_balanced_poses_train.csv').exists() else None


@pytest.fixture(scope='session')
def krang_data():
    path = krang_data_dir()
    if path is None:
        pytest.skip(
            'real Krang data not found: set KRANG_DATA or place shared/krang_data beside the '
            'checkout'
        )
    return path


@pytest.fixture
def context():
    """An rclpy context of the test's own, shut down after it."""
    rclpy = pytest.importorskip('rclpy')
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)
