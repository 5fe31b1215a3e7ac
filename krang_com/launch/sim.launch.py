"""The simulated Krang and the node set on its simulated CAN buses:
`ros2 launch krang_com sim.launch.py [plant:=mujoco] [plant_model:=EXTENDED_MODEL.yaml]`, the same
as `krang bringup --sim [--plant mujoco] [--plant-model EXTENDED_MODEL.yaml]`
(krang_cli/node_set.py). `ros2 launch krang_com sim.launch.py --show-args` lists the arguments.
"""

from krang_ros.launch_set import launch_description


def generate_launch_description():
    return launch_description(sim=True)
