"""The controller node (skeleton: starts, logs and spins).

The node issue fills it in over the cores of this package.
"""
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


class ControllerNode(Node):
    def __init__(self):
        super().__init__('controller')
        self.get_logger().info('controller node up (skeleton)')


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = ControllerNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
