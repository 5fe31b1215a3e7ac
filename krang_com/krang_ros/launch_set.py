"""The node set (krang_cli.node_set) as `ros2 launch` actions, for launch/*.launch.py. launch and
launch_ros exist only on a full ROS install; nothing but the launch files imports this module."""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from krang_cli.node_set import SIM_NODE, file_parameter, node_set

#: The simulated robot's launch arguments: sim_krang's parameter, its description (the same
#: choice as `krang bringup --sim --plant ... --plant-model ...`).
SIM_ARGUMENTS = {
    'plant': "the physics behind the simulated devices: 'reduced' (the controller's reduced WIP "
    "model) or 'mujoco' (the full body from the URDF)",
    'plant_model': 'an extended model written by `krang discrepancy` (its effects and values) '
    'applied to the plant; empty: none',
}


def sim_arguments():
    """DeclareLaunchArgument per SIM_ARGUMENTS, its default the value the set's parameter files
    give (so a plain `ros2 launch` runs what `krang bringup --sim` runs)."""
    return [
        DeclareLaunchArgument(
            name,
            default_value=str(file_parameter(SIM_NODE, name, sim=True, default='')),
            description=description,
        )
        for name, description in SIM_ARGUMENTS.items()
    ]


def launch_description(sim):
    """The set as a `ros2 launch` LaunchDescription (launch/robot.launch.py, sim.launch.py). The
    simulated robot's launch arguments come after its parameter files, so they win."""
    chosen = [
        {name: ParameterValue(LaunchConfiguration(name), value_type=str) for name in SIM_ARGUMENTS}
    ]
    nodes = [
        Node(
            package='krang_com',
            executable=spec.executable,
            name=spec.executable,
            parameters=list(spec.params_files) + (chosen if spec.executable == SIM_NODE else []),
            output='screen',
            emulate_tty=True,
        )
        for spec in node_set(sim)
    ]
    return LaunchDescription((sim_arguments() if sim else []) + nodes)
