"""Golem Krang's node set on its SocketCAN buses: `ros2 launch krang_com robot.launch.py`.
The same nodes and parameter files as `krang bringup` (krang_cli/node_set.py describes both)."""

from krang_ros.launch_set import launch_description


def generate_launch_description():
    return launch_description(sim=False)
