"""The simulated node set composed in one process, so that the same seed gives the same session.

As processes (`krang bringup --sim`, `krang demo --processes`) the nodes run concurrently. The
lockstep makes each wheel command act at a fixed simulated time, but the moments at which the other
inputs meet the physics (pose commands, PowerCube polls, a new beta, the session's calls) depend on
the scheduler. Composed, the same node classes share one rclpy context and one single-threaded
executor (krang_ros.executor), as a ROS 2 component container composes nodes, and their CAN buses
are python-can `virtual` buses read by a `bus_io.Pump`. DDS delivers between the nodes of one
participant synchronously (Fast DDS intra-process delivery: the message is in the reader's queue
when `publish` returns; test/test_composed.py checks it). So `advance()` can step the physics up to
the moment the answer to the next sample is due and then deliver everything, callbacks and frames,
until nothing is left: the simulator waits for the whole node set, not only for the wheel command,
and every message meets the physics at the same simulated moment in every run.
"""

import logging
import os
import time

import rclpy
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from krang_can_bridge.bus_io import Pump
from krang_ros.executor import StaticSingleThreadedExecutor
from krang_ros.entry import settle_garbage_collector
from krang_ros.spin import run_ready, without_qos_events

from .node_set import RECORDER, SIM_NODE, STOP_ORDER, node_set, params_files

log = logging.getLogger('krang.composed')

STARTUP_TIMEOUT_S = 30.0  # wall time for the bridge's drive start-up (SDO) before the physics runs


def node_classes():
    """Executable name -> node class (imported here: each pulls in its part of the package)."""
    from krang_adrc_controller.node import AdrcControllerNode
    from krang_bag.node import McapRecorder
    from krang_can_bridge.node import CanBridgeNode
    from krang_com_estimator.node import ComEstimatorNode
    from krang_pose_server.node import PoseServer
    from krang_ros.state_publisher import StatePublisherNode
    from krang_sim.node import SimKrangNode

    return {
        SIM_NODE: SimKrangNode,
        'can_bridge': CanBridgeNode,
        'adrc_controller': AdrcControllerNode,
        'pose_server': PoseServer,
        'com_estimator': ComEstimatorNode,
        'state_publisher': StatePublisherNode,
        RECORDER: McapRecorder,
    }


class CompositionError(RuntimeError):
    """The composed node set could not start."""


def _log_to(log_dir):
    """The nodes' logs to files in `log_dir`, as the nodes of `krang bringup --log-dir`: rclpy's
    through its file logger (ROS_LOG_DIR, read when this process first initialises rclpy), the
    Python loggers of the CAN libraries to nodes.log."""
    os.makedirs(log_dir, exist_ok=True)
    os.environ['ROS_LOG_DIR'] = str(log_dir)
    handler = logging.FileHandler(os.path.join(log_dir, 'nodes.log'))
    handler.setFormatter(logging.Formatter('%(asctime)s %(name)s %(levelname)s: %(message)s'))
    for name in ('canopen', 'can', 'krang_can_bridge'):
        logger = logging.getLogger(name)
        logger.addHandler(handler)
        logger.propagate = False


class ComposedSimulation:
    """sim_krang and the robot's nodes (and the recorder with `record`) in this process, with the
    parameter files of `krang bringup --sim` and `overrides` (node -> {name: value}); their logs
    in `log_dir` if given. The device map in the overrides must use `virtual` buses
    (session_devices_file(..., virtual=True))."""

    def __init__(self, overrides=None, record=None, log_dir=None):
        overrides = dict(overrides or {})
        if record:
            overrides[RECORDER] = {'output': str(record), **overrides.get(RECORDER, {})}
        args = ['--ros-args']
        for f in params_files(sim=True):
            args += ['--params-file', f]
        if log_dir is not None:
            _log_to(log_dir)
            args.append('--disable-stdout-logs')
        self.context = rclpy.Context()
        # Ctrl-C stays Python's KeyboardInterrupt: the caller stops between steps and closes
        rclpy.init(args=args, context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.executor = StaticSingleThreadedExecutor(context=self.context)
        self.pump = Pump()
        self.nodes = {}
        classes = node_classes()
        try:
            for spec in node_set(sim=True, record=bool(record)):
                name = spec.executable
                kwargs = {
                    'context': self.context,
                    'parameter_overrides': [
                        Parameter(k, value=v) for k, v in overrides.get(name, {}).items()
                    ],
                    # nothing from outside reaches a composed session (that is what makes it
                    # reproducible), so no parameter services: each is an entity of the one wait
                    # set, refilled at every wake (6 per node)
                    'start_parameter_services': False,
                }
                if name in (SIM_NODE, 'can_bridge'):
                    kwargs['pump'] = self.pump
                self.nodes[name] = without_qos_events(classes[name](**kwargs))
                self.executor.add_node(self.nodes[name])
            self.sim = self.nodes[SIM_NODE]
            self._share_the_clock()
            self._wait_for_drives()
            settle_garbage_collector()
        except BaseException:
            self.close()
            raise

    def _share_the_clock(self):
        """One /clock subscription for the set, as one TimeSource can drive several clocks: the
        bridge's time source sets every node's clock, the others stop listening. Four nodes on sim
        time each took every /clock message in a callback of its own, one per step each."""
        keeper = self.nodes['can_bridge']._time_source
        for name, node in self.nodes.items():
            if name not in ('can_bridge', SIM_NODE) and node._time_source.ros_time_is_active:
                node._time_source.detach_node()
                keeper.attach_clock(node.get_clock())

    def _wait_for_drives(self):
        """The bridge enables the drives through SDO from a thread of its own; the physics starts
        once they are enabled, so that the session starts from the same state in every run."""
        bridge = self.nodes['can_bridge']
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while any(s != 'enabled' for s in bridge.startup_status.values()):
            if time.monotonic() > deadline:
                raise CompositionError(f'the drives did not start: {bridge.startup_status}')
            self.deliver()
            time.sleep(0.001)

    def deliver(self):
        """Run every ready callback and hand over every queued frame, until neither is left."""
        while run_ready(self.executor) + self.pump.pump():
            pass

    def advance(self):
        """One step of the node set: the physics up to the answer to the next sample, then
        everything that sample caused."""
        self.sim.advance()
        self.deliver()

    @property
    def sim_time(self):
        return self.sim.sim.t

    def session_client(self):
        from krang_ros.session_client import SessionClient

        return without_qos_events(SessionClient(context=self.context, composed=self))

    def close(self):
        """Stop the nodes in STOP_ORDER (the recorder last, after the rest was delivered)."""
        for name in [n for n in STOP_ORDER if n in self.nodes]:
            if name == RECORDER:
                self.deliver()
            node = self.nodes.pop(name)
            if hasattr(node, 'close'):
                node.close()
            self.executor.remove_node(node)
            node.destroy_node()
        self.executor.shutdown()
        rclpy.try_shutdown(context=self.context)
