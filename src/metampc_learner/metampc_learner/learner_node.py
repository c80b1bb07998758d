"""The learner node (skeleton: starts, logs and spins).

The node issue fills it in over the cores of this package.
"""
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


class LearnerNode(Node):
    def __init__(self):
        super().__init__('learner')
        self.get_logger().info('learner node up (skeleton)')


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = LearnerNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
