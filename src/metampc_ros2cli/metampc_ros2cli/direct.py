"""The short-lived node every verb talks through (ros2cli's DirectNode, without a daemon).

It is created, spins for ``--spin-time`` seconds so that discovery sees the graph, and is
destroyed with its context when the verb ends.
"""
import argparse
import os
from typing import Any

DEFAULT_SPIN_TIME = 0.5     # s, as ros2cli's DirectNode
# s: how much longer a verb that names a topic, service or node waits for discovery to show it
# (ros2cli asks its daemon, whose graph is already complete; a fresh node may not be after
# --spin-time: with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, as the tests run, a new node
# often sees the others only at their next announcement, about 3 s later).
DISCOVERY_GRACE_S = 5.0
NODE_NAME_PREFIX = '_ros2cli'
SLICE_S = 0.1      # s: longest a wait for an answer holds off Ctrl-C


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """ros2cli's --spin-time and --use-sim-time."""
    parser.add_argument('--spin-time', type=float, default=DEFAULT_SPIN_TIME,
                        help='Spin time in seconds to wait for discovery')
    parser.add_argument('-s', '--use-sim-time', action='store_true',
                        help='Enable ROS simulation time')


class DirectNode:
    """``with DirectNode(args) as node:`` an rclpy node that has spun ``args.spin_time`` s."""

    def __init__(self, args: Any, node_name: str = '') -> None:
        import rclpy
        from rclpy.parameter import Parameter
        self._rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(
            node_name or f'{NODE_NAME_PREFIX}_{os.getpid()}', context=self.context,
            start_parameter_services=False,
            parameter_overrides=[Parameter('use_sim_time', value=getattr(args, 'use_sim_time',
                                                                         False))])
        self.executor = rclpy.executors.SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.spin_for(getattr(args, 'spin_time', DEFAULT_SPIN_TIME))

    def spin_for(self, seconds: float) -> None:
        """Spin the node's callbacks for `seconds` of wall time."""
        import time
        end = time.monotonic() + seconds
        while self.context.ok():
            left = end - time.monotonic()
            if left <= 0:
                return
            self.executor.spin_once(timeout_sec=left)

    def __enter__(self) -> Any:
        return self.node

    def __exit__(self, *exc: Any) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


def wait_future(node: Any, future: Any) -> None:
    """Spin `node` (a DirectNode's) until `future` is done or its context shuts down, in
    slices of SLICE_S: Python runs its SIGINT handler only between them, so Ctrl-C ends the
    wait at once (one unbounded rcl wait, as spin_until_future_complete does, held it off
    until the answer came: forever, for a server that never answers)."""
    while not future.done() and node.context.ok():
        node.executor.spin_once(timeout_sec=SLICE_S)


def wait_for(node: Any, found: Any, timeout: float = DISCOVERY_GRACE_S) -> Any:
    """Spin `node` (a DirectNode's) until `found()` returns something true, returned, or
    `timeout` s passed (then its last value)."""
    import time
    end = time.monotonic() + timeout
    value = found()
    while not value and node.context.ok() and time.monotonic() < end:
        node.executor.spin_once(timeout_sec=0.05)
        value = found()
    return value
