"""The simulated Krang and the node set on its simulated CAN buses:
`ros2 launch krang_com sim.launch.py`, the same as `krang bringup --sim` (krang_cli/node_set.py).
"""

from krang_ros.launch_set import launch_description


def generate_launch_description():
    return launch_description(sim=True)
