"""The one way our nodes run: init, spin until Ctrl-C or shutdown, then close and shut down
cleanly, with exit code 0 and no traceback however early the signal comes."""

import sys

import rclpy
from rclpy.executors import ExternalShutdownException

from .params import ParameterError


def run_node(node_class, args=None):
    """Spin one node; `node.close()` (if the node has one) releases its hardware before
    destruction. A SIGINT or SIGTERM while the node is still being built (rclpy then shuts the
    context down under the constructor, whose next ROS call fails) is a clean exit too."""
    rclpy.init(args=args)
    node = None
    try:
        node = node_class()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ParameterError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    except Exception:
        if rclpy.ok():
            raise
        # the context was shut down by a signal under a ROS call: a requested stop, not a fault
    finally:
        if node is not None:
            if hasattr(node, 'close'):
                node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
