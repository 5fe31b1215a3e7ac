"""The one way our nodes run: init, spin until Ctrl-C or shutdown, then close and shut down
cleanly."""
import rclpy
from rclpy.executors import ExternalShutdownException


def run_node(node_class, args=None):
    """Spin one node; `node.close()` (if the node has one) releases its hardware before
    destruction."""
    rclpy.init(args=args)
    node = node_class()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if hasattr(node, 'close'):
            node.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
