"""The node set, described once.

`krang bringup` starts it as processes and `launch/*.launch.py` turn it into `ros2 launch` actions
(krang_ros.launch_set), so the two can never start different executables or load different
parameter files. No ROS import here.
"""

from dataclasses import dataclass

from krang_model.config import config_path, load_config

#: The robot's own nodes, in start order (the bridge first: it owns the drives). state_publisher
#: puts /robot_description, /tf and the CoM in every recording, so that a bag opens in Foxglove
#: with the robot drawn and posed.
ROBOT_NODES = ('can_bridge', 'adrc_controller', 'pose_server', 'com_estimator', 'state_publisher')
SIM_NODE = 'sim_krang'
RECORDER = 'mcap_recorder'
#: Stop order: commands first, the bridge (which sends zero current on exit) after the controller,
#: the simulator after the bridge, the recorder last so that it sees everything.
STOP_ORDER = (
    'pose_server',
    'adrc_controller',
    'com_estimator',
    'state_publisher',
    'can_bridge',
    SIM_NODE,
    RECORDER,
)

#: Parameter files of config/, later files win. sim_params.yaml holds every setting of the
#: simulated node set that differs from the robot's, with the reason.
ROBOT_PARAMS = ('controller.yaml', 'krang_params.yaml')
SIM_PARAMS = ('sim_params.yaml',)


@dataclass(frozen=True)
class NodeSpec:
    """One node of the set: the executable (also the node name) and its parameter files."""

    executable: str
    params_files: tuple


def params_files(sim, extra=()):
    """The parameter files every node of the set loads, in order (later files win)."""
    names = ROBOT_PARAMS + (SIM_PARAMS if sim else ())
    return tuple(str(config_path(n)) for n in names) + tuple(str(p) for p in extra)


def file_parameter(node, name, sim, default=None):
    """The value the set's parameter files give parameter `name` of `node` (later files win), or
    `default` where none sets it."""
    value = default
    for path in params_files(sim):
        value = load_config(path).get(node, {}).get('ros__parameters', {}).get(name, value)
    return value


def node_set(sim, record=False, extra_params=()):
    """The nodes to start, in start order: the recorder first (so it sees the start-up), the
    simulated robot before the bridge, then the robot's nodes."""
    files = params_files(sim, extra_params)
    names = ((RECORDER,) if record else ()) + ((SIM_NODE,) if sim else ()) + ROBOT_NODES
    return tuple(NodeSpec(name, files) for name in names)
