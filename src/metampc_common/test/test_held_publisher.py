"""HeldPublisher's retry rule against a publisher that refuses as DDS does when a reader that
keeps all is full (rclpy raises 'cannot publish data')."""
import pytest

from metampc_common.held_publisher import BACKLOG, HELD, held_qos, HeldPublisher, HoldConfig


class Full(Exception):
    """rclpy's RCLError text for a publish whose writer history is full."""

    def __init__(self):
        super().__init__('Failed to publish: cannot publish data, at rmw_publish.cpp:66')


class FakePublisher:
    topic_name = '/y'

    def __init__(self, refusals: int, error=Full):
        self.refusals, self.error, self.sent = refusals, error, []

    def publish(self, msg):
        if self.refusals:
            self.refusals -= 1
            raise self.error()
        self.sent.append(msg)


def test_a_refused_publish_is_retried_until_it_goes_out():
    fake = FakePublisher(refusals=3)
    pub = HeldPublisher(fake, HoldConfig())
    assert pub.publish('y0') and pub.publish('y1')
    assert fake.sent == ['y0', 'y1'] and pub.held == 1 and pub.dropped == 0
    assert pub.held_s > 0


def test_a_message_that_finds_no_room_in_time_is_dropped_counted_and_reported():
    told = []
    pub = HeldPublisher(FakePublisher(refusals=10 ** 9), HoldConfig(hold_timeout=0.05),
                        told.append)
    assert not pub.publish('y0')
    assert pub.dropped == 1 and pub.held_s >= 0.05
    assert len(told) == 1 and told[0].startswith('/y: no room for a message in 0.05 s')


def test_other_errors_are_not_retried():
    with pytest.raises(RuntimeError):
        HeldPublisher(FakePublisher(1, RuntimeError), HoldConfig()).publish('y0')


def test_the_switch_picks_the_writers_profile():
    assert held_qos(HoldConfig()) is HELD
    assert held_qos(HoldConfig(hold_for_readers=False)) is BACKLOG
