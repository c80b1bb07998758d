"""Shared helpers for tests that start real ROS 2 processes.

Every process is started through `ros2 run` (the shim or a real ros2) in the test session's
isolated domain (see conftest.py) and is stopped by the test that started it: use the ``procs``
fixture (a metampc_bringup.processes.ProcessGroup).
"""
from metampc_bringup.processes import ProcessGroup, ros_args, session_pids  # noqa: F401
from metampc_bringup.spun_node import SpunNode


class TestNode(SpunNode):
    """An rclpy node spun in a background thread, for probing the graph from a test."""

    __test__ = False    # not a test class, though imported into test modules

    def __init__(self, name: str = 'metampc_test_probe'):
        super().__init__(name)
