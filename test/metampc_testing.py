"""Shared helpers for tests that start real ROS 2 processes.

Every process is started through `ros2 run` (the shim or a real ros2) in the test session's
isolated domain (see conftest.py) and is stopped by the test that started it: use the ``procs``
fixture (a metampc_bringup.processes.ProcessGroup) or :func:`ros_processes`.
"""
import contextlib
import threading
import time
from typing import Callable, Iterator, List

from metampc_bringup.processes import ProcessGroup, ros_args, session_pids  # noqa: F401
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node


class TestNode:
    """An rclpy node spun in a background thread, for probing the graph from a test."""

    def __init__(self, name: str = 'metampc_test_probe'):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def wait_for(self, predicate: Callable[[], bool], timeout: float, what: str) -> None:
        """Poll predicate until true; AssertionError naming `what` after timeout seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return
            time.sleep(0.05)
        raise AssertionError(f'timed out after {timeout} s waiting for {what}')

    def node_names(self) -> List[str]:
        return [n for n, _ in self.node.get_node_names_and_namespaces()]

    def wait_for_node(self, name: str, timeout: float = 30.0) -> None:
        self.wait_for(lambda: name in self.node_names(), timeout, f'node {name!r}')

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=5.0)


@contextlib.contextmanager
def ros_processes(log_dir: str) -> Iterator[ProcessGroup]:
    group = ProcessGroup(log_dir)
    try:
        yield group
    finally:
        group.stop_all()
