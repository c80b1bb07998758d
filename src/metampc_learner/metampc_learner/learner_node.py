"""The learner node (skeleton: starts, logs and spins).

The node issue fills it in over the cores of this package.
"""
from metampc_plant.node_main import run_node
from rclpy.node import Node


class LearnerNode(Node):
    def __init__(self):
        super().__init__('learner')
        self.get_logger().info('learner node up (skeleton)')


def main(args=None) -> int:
    return run_node(LearnerNode, 'learner', args)
