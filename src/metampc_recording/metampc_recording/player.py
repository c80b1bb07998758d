"""Playback of a recording onto ROS topics, as ``ros2 bag play`` does.

Each recorded topic gets a publisher with the QoS rosbag2 would offer for it
(:func:`~metampc_recording.rosbag2_qos.offer_for_recorded`), so a latched topic replays
latched; the recorded CDR bytes are published unchanged at the recorded log-time spacing
divided by ``rate``, from ``start_offset`` s, once or (``loop``) until interrupted.
:func:`run_player` streams the file in recorded order rather than holding it. ``delay`` gives
discovery a fixed time and ``wait_for_subscribers`` (not in ``ros2 bag play``) waits until
every volatile topic has a subscriber that receives its first message. Used by
``scripts/replay.py --play`` and ``ros2 bag play``; see docs/recording.md.
"""
import time
from dataclasses import dataclass, field
from typing import Dict, List

from metampc_common.message_types import message_class
from metampc_recording.rclpy_adapters import qos_to_rclpy
from metampc_recording.recording_reader import read_recording, Recording
from metampc_recording.rosbag2_qos import offer_for_recorded, profiles_from_yaml, QosProfile
import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node


@dataclass
class PlayConfig:
    """Options of a playback.

    Attributes:
        rate: speed factor (2.0 plays twice as fast); > 0.
        delay: seconds between creating the publishers and the first message (lets
            subscribers discover them, as ``ros2 bag play --delay``).
        topics: topics to play (default: all).
        ack_timeout: seconds to wait at the end for reliable subscribers to acknowledge.
        wait_for_subscribers: after the delay, wait up to this many seconds until every
            volatile topic played has at least one matched subscriber, then (as long again)
            until each topic's first message is acknowledged by its reliable subscribers, so
            that none loses a message (0: do not wait).
        start_offset: seconds of the recording to skip: playback starts at the log time of
            the first message played plus this (``ros2 bag play --start-offset``).
        loop: start again from the beginning at the end, until interrupted (``--loop``); the
            delay is slept before every pass, as rosbag2 does.
    """

    rate: float = 1.0
    delay: float = 0.0
    topics: List[str] = field(default_factory=list)
    ack_timeout: float = 2.0
    wait_for_subscribers: float = 0.0
    start_offset: float = 0.0
    loop: bool = False

    def validate(self) -> None:
        """ValueError for a non-positive rate or a negative delay, timeout or offset."""
        if not self.rate > 0 or min(self.delay, self.ack_timeout, self.wait_for_subscribers,
                                    self.start_offset) < 0:
            raise ValueError('rate must be positive; delay, ack_timeout, '
                             'wait_for_subscribers and start_offset non-negative')


def _offer(text: str) -> QosProfile:
    try:
        return offer_for_recorded(profiles_from_yaml(text))
    except ValueError:
        return QosProfile()


def play(recording: Recording, node: Node, config: PlayConfig) -> Dict[str, int]:
    """Publish the recording's messages from `node`; returns the count published per topic."""
    config.validate()
    names = config.topics or list(recording.topics)
    unknown = sorted(set(names) - set(recording.topics))
    if unknown:
        raise ValueError(f'not in the recording: {", ".join(unknown)}')
    publishers, volatile = {}, []
    for name in names:
        topic = recording.topics[name]
        offer = _offer(topic.offered_qos_profiles)
        publishers[name] = node.create_publisher(
            message_class(topic.type_name), name, qos_to_rclpy(offer))
        if offer.durability != 'transient_local':
            volatile.append(publishers[name])
    time.sleep(config.delay)
    deadline = time.monotonic() + config.wait_for_subscribers
    while (time.monotonic() < deadline
           and any(p.get_subscription_count() == 0 for p in volatile)):
        time.sleep(0.01)
    # A match counted above is the publisher's side of it; the subscriber's side can come
    # later, and what is published before that reaches the subscriber only from the
    # publisher's history (10 deep). So the first message of each volatile topic waits until
    # every matched reliable subscriber has acknowledged it (up to wait_for_subscribers s),
    # and the playback's clock waits with it.
    unconfirmed = {name for name, publisher in publishers.items()
                   if config.wait_for_subscribers and publisher in volatile}
    counts = {name: 0 for name in names}
    first = next(recording.raw(publishers), None)
    start_log = (first.log_time if first else 0) + round(config.start_offset * 1e9)
    while True:
        start_wall, played = time.monotonic(), 0
        for message in recording.raw(publishers):   # streamed unless read with the messages
            if message.log_time < start_log:
                continue
            due = start_wall + (message.log_time - start_log) * 1e-9 / config.rate
            if due > time.monotonic():
                time.sleep(due - time.monotonic())
            publisher = publishers[message.topic]
            publisher.publish(message.data)
            if message.topic in unconfirmed:
                unconfirmed.discard(message.topic)
                paused = time.monotonic()
                publisher.wait_for_all_acked(Duration(seconds=config.wait_for_subscribers))
                start_wall += time.monotonic() - paused
            counts[message.topic] += 1
            played += 1
        if not (config.loop and played):
            break
        time.sleep(config.delay)
    for publisher in publishers.values():
        publisher.wait_for_all_acked(Duration(seconds=config.ack_timeout))
    return counts


def run_player(path: str, config: PlayConfig) -> Dict[str, int]:
    """Play `path` (MCAP file or run folder) from a node of its own, then shut down."""
    config.validate()
    recording = read_recording(path, messages=False)    # streamed: any size
    rclpy.init()
    node = Node('metampc_player')
    try:
        return play(recording, node, config)
    except (KeyboardInterrupt, ExternalShutdownException):
        return {}
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
