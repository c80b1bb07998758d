"""Foxglove live view: serves the graph's topics over the Foxglove WebSocket protocol.

``ros2 run metampc_recording foxglove [--ros-args -p port:=8765 -p host:=127.0.0.1]``, then
connect Foxglove to ``ws://HOST:PORT``. Subscribes (``raw=True``) each topic the recorder would
take, once it has a publisher, with the recorder's QoS choice, and passes its CDR bytes to
:class:`~metampc_recording.foxglove_server.LiveServer` unchanged, stamped with their receive
time on the node clock. Refuses a bad parameter or a port in use (one error line, exit 2).
Parameters: :data:`metampc_recording.foxglove_params.PARAMETERS`; docs/foxglove.md.
"""
import sys
from functools import partial
from typing import Dict, Set

from metampc_common.message_types import message_class
from metampc_common.node_main import declare_parameters, run_node
from metampc_common.params import ParameterError
from metampc_recording.foxglove_params import parse_params, PARAMETERS
from metampc_recording.foxglove_server import LiveServer
from metampc_recording.graph_topics import default_topic, new_topics, resolve_topics
from metampc_recording.msg_schema import DefinitionNotFoundError
from metampc_recording.rclpy_adapters import qos_to_rclpy
from metampc_recording.rosbag2_qos import request_for_offers
from rclpy.clock import Clock, ClockType
from rclpy.node import Node


class FoxgloveNode(Node):
    """Thin adapter: graph discovery and raw subscriptions in, LiveServer out.

    Raises:
        ParameterError: a bad parameter, or a server that cannot listen on host:port.
    """

    def __init__(self):
        super().__init__('foxglove')
        self.config = parse_params(declare_parameters(self, PARAMETERS))
        self._wanted = resolve_topics(self, self.config.topics)
        self._served: Dict[str, object] = {}
        self._skipped: Set[str] = set()
        try:
            self.server = LiveServer(f'metampc {self.get_fully_qualified_name()}',
                                     self.config.host, self.config.port,
                                     clock=lambda: self.get_clock().now().nanoseconds)
        except OSError as err:
            raise ParameterError(f'port: {err}') from None
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(self.config.discovery_period, self._discover, clock=steady)
        self.get_logger().info(f'serving ws://{self.config.host}:{self.server.port} '
                               f'({", ".join(sorted(self._wanted)) or "all topics"})')
        self._discover()

    def _selected(self, topic: str) -> bool:
        return topic in self._wanted if self._wanted else default_topic(topic,
                                                                        self.get_namespace())

    def _skip(self, topic: str, reason: str) -> None:
        self._skipped.add(topic)
        self.get_logger().warning(f'not serving {topic}: {reason}')

    def _discover(self) -> None:
        """Serve every selected topic that has a publisher and is not served yet."""
        known = self._served.keys() | self._skipped
        for topic, type_name, offered, _ in new_topics(self, known, self._selected, self._skip):
            request = request_for_offers(offered, self.config.qos_depth)
            try:
                msg_type = message_class(type_name)
                self.server.add_topic(topic, type_name, request.durability == 'transient_local')
            except (ImportError, AttributeError, ValueError, DefinitionNotFoundError) as err:
                self._skip(topic, f'type {type_name} unavailable ({err})')
                continue
            self._served[topic] = self.create_subscription(
                msg_type, topic, partial(self._on_message, topic), qos_to_rclpy(request),
                raw=True)
            self.get_logger().info(f'serving {topic} [{type_name}] '
                                   f'({request.reliability}, {request.durability})')

    def _on_message(self, topic: str, data: bytes) -> None:
        self.server.publish(topic, data, self.get_clock().now().nanoseconds)

    def destroy_node(self) -> None:
        """Stop the server (its clients are disconnected), then destroy the node."""
        self.server.close()
        super().destroy_node()


def main(args=None) -> int:
    """`ros2 run metampc_recording foxglove`; returns the exit code."""
    return run_node(FoxgloveNode, 'foxglove', args)


if __name__ == '__main__':
    sys.exit(main())
