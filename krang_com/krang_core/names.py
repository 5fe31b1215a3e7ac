"""Topic, service and action names of the node graph, spelled once for every node, client,
recorder, offline tool and test."""

JOINT_STATES = '/joint_states'
IMU = '/imu/data'
WHEEL_EFFORT_CMD = '/wheel_effort_cmd'
JOINT_POSITION_CMD = '/joint_position_cmd'
BALANCED_POSE = '/balanced_pose'
BETA = '/com_estimator/beta'
COM = '/com_estimator/com'
POSE_TARGET = '/pose_server/target'
DIAGNOSTICS = '/diagnostics'
CLOCK = '/clock'  # ROS simulated time, published by sim_krang
GROUND_TRUTH = '/sim_krang/ground_truth'  # the simulator's truth, for evaluation only
DRIVE_FAULT = '/can_bridge/drive_fault'  # latched DriveFault
ARM_FAULT = '/can_bridge/arm_fault'  # latched ArmFault: an arm module stopped answering
MODE = '/adrc_controller/mode'  # latched ControllerMode
BALANCE_CONVERGED = '/adrc_controller/balance_converged'  # latched Bool: balance estimate settled
STAND_ESTIMATE = '/adrc_controller/stand_estimate'  # latched StandEstimate: a caught stand-up

BASE_PITCH = 'base_pitch'  # the extra "joint" of /balanced_pose in older bags (JointState)
WHEEL_JOINTS = ('JLWheel', 'JRWheel')

# Services: the node that serves each and the name it is served under.
# The controller's operator controls (README "Running on the robot"): std_srvs SetBool, Trigger.
ENABLE = '/adrc_controller/enable'
HALT = '/adrc_controller/halt'
CONTROLLER_RECOVER = '/adrc_controller/recover'
NEXT_POSE = '/pose_server/next_pose'  # Trigger: starts the move of MOVE_TO_NEXT_POSE
POSE_RESET = '/pose_server/reset'
SAVE = '/com_estimator/save'
ESTIMATOR_RESET = '/com_estimator/reset'
BRIDGE_RECOVER = '/can_bridge/recover'  # std_srvs/Trigger: drive/arm fault recovery

# Actions (krang_com_interfaces/action): the long calls, with feedback, result and cancel.
STAND_UP_ACTION = '/adrc_controller/stand_up'  # StandUp
SIT_DOWN_ACTION = '/adrc_controller/sit_down'  # SitDown
MOVE_TO_NEXT_POSE = '/pose_server/move_to_next_pose'  # MoveToNextPose


def relative(name):
    """A name above as a name relative to the node's namespace: it resolves to the name above in
    the default namespace and moves with __ns (ROS convention for topics and clients)."""
    return name.lstrip('/')


def private(name):
    """A service or action name above as the serving node's private name ('~/save'): it moves
    with __ns and __node."""
    return '~/' + name.rsplit('/', 1)[1]
