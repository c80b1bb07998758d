"""A publisher held back by a reader that keeps all: the recorder loses no message, however
fast the lockstep loop runs.

These writers keep all (:data:`HELD`): DDS holds a sample until every reliable reader has
acknowledged it, a keep-all reader whose history is full acknowledges no more, and the
writer's publish then fails after its max_blocking_time (100 ms); :class:`HeldPublisher`
retries it until ``hold_timeout`` has passed, then drops the message for every reader, counts it
and reports it through ``on_timeout`` (a reader that stopped must not stop the loop for good).
Readers that keep the last N never hold the loop back. Why and what was measured:
docs/nodes.md#a-recording-that-is-complete-at-any-speed, docs/speed.md.
"""
import time
from typing import Callable, Optional

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from metampc_common.hold_config import HoldConfig
from metampc_common.qos import BACKLOG

# The writers of y, u and mpc_status: reliable, volatile, keep all (bounded by DDS's resource
# limits: a full history blocks publish, it does not drop).
HELD = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                  durability=DurabilityPolicy.VOLATILE)
RETRY_S = 0.001     # pause between two tries of a held-back publish, s

__all__ = ['BACKLOG', 'HELD', 'HeldPublisher', 'HoldConfig', 'held_qos']


def held_qos(config: HoldConfig) -> QoSProfile:
    """The writers' QoS profile: :data:`HELD`, or qos.BACKLOG without ``hold_for_readers``."""
    return HELD if config.hold_for_readers else BACKLOG


class HeldPublisher:
    """Wraps an rclpy publisher created with ``held_qos(config)``: ``publish`` waits while a
    reader that keeps all is full.

    Attributes:
        held: publishes that had to wait; held_s: total s waited; dropped: messages given up
            after hold_timeout.
    """

    def __init__(self, publisher, config: HoldConfig,
                 on_timeout: Optional[Callable[[str], None]] = None):
        """publisher: an rclpy Publisher; on_timeout(message): told of each dropped message."""
        self.publisher = publisher
        self.config = config
        self._on_timeout = on_timeout or (lambda _message: None)
        self.held = self.dropped = 0
        self.held_s = 0.0

    def publish(self, msg) -> bool:
        """Publish, waiting up to hold_timeout for room; whether it went out."""
        start = None
        while True:
            try:
                self.publisher.publish(msg)
                break
            except Exception as err:    # rclpy's RCLError: DDS's history is full
                if 'cannot publish data' not in str(err):
                    raise
            now = time.monotonic()
            if start is None:
                start = now
                self.held += 1
            elif now - start >= self.config.hold_timeout:
                self.held_s += now - start
                self.dropped += 1
                self._on_timeout(f'{self.publisher.topic_name}: no room for a message in '
                                 f'{self.config.hold_timeout:g} s (a reader that keeps all, '
                                 'the recorder, has stopped taking them); dropped it')
                return False
            time.sleep(RETRY_S)
        if start is not None:
            self.held_s += time.monotonic() - start
        return True

    def __getattr__(self, name):
        """Everything else (get_subscription_count, topic_name, ...) is the publisher's."""
        return getattr(self.publisher, name)
