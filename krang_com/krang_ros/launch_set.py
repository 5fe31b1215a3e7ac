"""The node set (krang_cli.node_set) as `ros2 launch` actions, for launch/*.launch.py. launch and
launch_ros exist only on a full ROS install; nothing but the launch files imports this module."""

from launch import LaunchDescription
from launch_ros.actions import Node

from krang_cli.node_set import node_set


def launch_description(sim):
    """The set as a `ros2 launch` LaunchDescription (launch/robot.launch.py, sim.launch.py)."""
    return LaunchDescription(
        [
            Node(
                package='krang_com',
                executable=spec.executable,
                name=spec.executable,
                parameters=list(spec.params_files),
                output='screen',
                emulate_tty=True,
            )
            for spec in node_set(sim)
        ]
    )
