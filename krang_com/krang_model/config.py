"""Where the installed package keeps its config, and the robot's drive-train/contact parameters."""

import os
import sys
from functools import lru_cache
from pathlib import Path

import yaml

PACKAGE_NAME = 'krang_com'
REPO_CONFIG = Path(__file__).resolve().parents[1] / 'config'


def config_dir():
    """config/ of the source tree, else share/krang_com/config of the install (colcon or pip)."""
    if REPO_CONFIG.is_dir():
        return REPO_CONFIG
    prefixes = [sys.prefix] + os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
    for prefix in prefixes:
        candidate = Path(prefix) / 'share' / PACKAGE_NAME / 'config'
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(
        f'cannot find the {PACKAGE_NAME} config directory (looked in {REPO_CONFIG} '
        f'and share/{PACKAGE_NAME}/config under {prefixes})'
    )


def config_path(name):
    return config_dir() / name


@lru_cache(maxsize=None)
def _load_yaml(path):
    with open(path) as f:
        return yaml.safe_load(f)


def load_config(name):
    """A YAML file of config/ as a dict (cached; copy before mutating)."""
    return _load_yaml(str(config_path(name)))


def robot_config():
    return load_config('robot.yaml')
