"""Topic and service names of the node graph, spelled once for every node, client, recorder,
offline tool and test."""

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
DRIVE_FAULT = '/can_bridge/drive_fault'  # latched reason of a drive fault, '' when clear
MODE = '/adrc_controller/mode'  # latched controller mode (Mode values)
BALANCE_CONVERGED = '/adrc_controller/balance_converged'  # latched Bool: balance estimate settled

# latched (n_beta + 1) x n_beta Float64MultiArray: row 0 beta, rows 1.. its covariance (zeros when
# the estimator has none); the pose server's adaptive choice reads it
POSTERIOR = '/com_estimator/posterior'

BASE_PITCH = 'base_pitch'  # the extra "joint" of /balanced_pose
WHEEL_JOINTS = ('JLWheel', 'JRWheel')

# Services: the node that serves each and the name it is served under.
ENABLE = '/adrc_controller/enable'
STAND_UP = '/adrc_controller/stand_up'  # std_srvs/Trigger; operator controls of
SIT_DOWN = '/adrc_controller/sit_down'  # the controller, README "Running on the robot"
HALT = '/adrc_controller/halt'
CONTROLLER_RECOVER = '/adrc_controller/recover'
NEXT_POSE = '/pose_server/next_pose'
POSE_RESET = '/pose_server/reset'
SAVE = '/com_estimator/save'
ESTIMATOR_RESET = '/com_estimator/reset'
BRIDGE_RECOVER = '/can_bridge/recover'  # std_srvs/Trigger: fault reset + enable, or why not


def relative(name):
    """A name above as a name relative to the node's namespace: it resolves to the name above in
    the default namespace and moves with __ns (ROS convention for topics and clients)."""
    return name.lstrip('/')


def private(name):
    """A service name above as the serving node's private name ('~/save'): it moves with __ns
    and __node."""
    return '~/' + name.rsplit('/', 1)[1]
