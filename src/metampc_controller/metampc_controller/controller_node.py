"""The controller node (skeleton: starts, logs and spins).

The node issue fills it in over the cores of this package.
"""
from metampc_plant.node_main import run_node
from rclpy.node import Node


class ControllerNode(Node):
    def __init__(self):
        super().__init__('controller')
        self.get_logger().info('controller node up (skeleton)')


def main(args=None) -> int:
    return run_node(ControllerNode, 'controller', args)
