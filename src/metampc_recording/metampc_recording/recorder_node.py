"""Recorder node: subscribes with raw=True and writes the CDR bytes to MCAP as rosbag2 does.

``ros2 run metampc_recording recorder --ros-args -p output:=runs/x/recording.mcap``. Subscribes
each topic (``topics``, or every one under its namespace but ``/rosout``,
``/parameter_events``, hidden topics and ``/clock``) once it has a publisher, with rosbag2's
QoS choice (:mod:`metampc_recording.rosbag2_qos`); log time = receive time on the node clock,
publish time = the publisher's source time; the writing is
:class:`~metampc_recording.mcap_writer.Rosbag2McapWriter`. SIGINT/SIGTERM close the file
(summary with statistics), exit 0. Refuses a bad parameter or an existing ``output`` (one
line, exit 2, the file left alone). Parameters:
:data:`metampc_recording.recorder_config.PARAMETERS`; docs/recording.md.
"""
import os
import sys
from functools import partial
from typing import Dict, Set

from metampc_common.message_types import message_class
from metampc_common.node_main import declare_parameters, run_node
from metampc_common.params import ParameterError
from metampc_recording.graph_topics import default_topic, new_topics, resolve_topics
from metampc_recording.mcap_writer import Rosbag2McapWriter
from metampc_recording.msg_schema import DefinitionNotFoundError
from metampc_recording.rclpy_adapters import qos_to_rclpy
from metampc_recording.recorder_config import parse_params, PARAMETERS
from metampc_recording.rosbag2_qos import request_for_offers
from rclpy.clock import Clock, ClockType
from rclpy.node import Node


class RecorderNode(Node):
    """Thin adapter: graph discovery and raw subscriptions in, Rosbag2McapWriter out.

    Raises:
        ParameterError: a bad parameter, or an `output` that exists (left untouched).
    """

    def __init__(self):
        super().__init__('recorder')
        self.config = parse_params(declare_parameters(self, PARAMETERS))
        writer_config = self.config.writer_config()
        self._wanted = resolve_topics(self, self.config.topics)
        if self._wanted and self.config.record_clock:
            self._wanted.add('/clock')
        os.makedirs(os.path.dirname(os.path.abspath(writer_config.path)), exist_ok=True)
        try:
            self.writer = Rosbag2McapWriter(writer_config)
        except FileExistsError:
            raise ParameterError(f'output {writer_config.path} exists; '
                                 'refusing to overwrite it') from None
        except ValueError as err:
            raise ParameterError(str(err)) from None
        self._recorded: Dict[str, object] = {}
        self._skipped: Set[str] = set()
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(self.config.discovery_period, self._discover, clock=steady)
        if self.config.flush_period > 0:
            self.create_timer(self.config.flush_period, self.writer.flush, clock=steady)
        self.get_logger().info(f'recording to {writer_config.path} '
                               f'({", ".join(sorted(self._wanted)) or "all topics"})')
        self._discover()

    def _selected(self, topic: str) -> bool:
        if self._wanted:
            return topic in self._wanted
        return default_topic(topic, self.get_namespace(), self.config.record_clock)

    def _skip(self, topic: str, reason: str) -> None:
        self._skipped.add(topic)
        self.get_logger().warning(f'not recording {topic}: {reason}')

    def _discover(self) -> None:
        """Subscribe to every selected topic that has a publisher and is not recorded yet."""
        known = self._recorded.keys() | self._skipped
        for topic, type_name, offered, type_hash in new_topics(self, known, self._selected,
                                                               self._skip):
            try:
                msg_type = message_class(type_name)
                self.writer.add_topic(topic, type_name, offered, type_hash)
            except (ImportError, AttributeError, ValueError, DefinitionNotFoundError) as err:
                self._skip(topic, f'type {type_name} unavailable ({err})')
                continue
            request = request_for_offers(offered, self.config.qos_depth)
            self._recorded[topic] = self.create_subscription(
                msg_type, topic, partial(self._on_message, topic), qos_to_rclpy(request),
                raw=True)
            self.get_logger().info(f'recording {topic} [{type_name}] '
                                   f'({request.reliability}, {request.durability})')

    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        self.writer.write(topic, data, self.get_clock().now().nanoseconds,
                          info['source_timestamp'], info['publication_sequence_number'] or 0)

    def destroy_node(self) -> None:
        """Finish the MCAP file (summary, statistics), destroy the node, report the counts."""
        self.writer.close()
        super().destroy_node()
        counts = self.writer.topics
        # Logged after destruction, as the plant does: after a signal, /rosout is gone.
        self.get_logger().info(f'wrote {sum(counts.values())} messages on {len(counts)} '
                               f'topics to {self.writer.config.path}')


def main(args=None) -> int:
    """`ros2 run metampc_recording recorder --ros-args -p output:=...`; returns the exit code."""
    return run_node(RecorderNode, 'recorder', args)


if __name__ == '__main__':
    sys.exit(main())
