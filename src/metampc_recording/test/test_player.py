"""The player's wait for subscribers (player.play), against a node whose publishers record what
they are asked, in order and when: no ROS graph, so the timing of discovery is the test's.

A subscriber's side of a match can complete after the publisher counts it; what is published
in between reaches it only from the publisher's history. A player that waits for subscribers
must therefore see each volatile topic's first message acknowledged before it goes on.
"""
import time

from metampc_recording.mcap_writer import McapWriterConfig, Rosbag2McapWriter
from metampc_recording.player import play, PlayConfig
from metampc_recording.recording_reader import read_recording
from metampc_recording.rosbag2_qos import QosProfile
import pytest

ACK_S = 0.3         # how long the subscribers take to acknowledge a first message
SPACING_S = 0.05    # between the recorded messages


class Publisher:
    def __init__(self, topic: str, events: list):
        self.topic, self.events = topic, events

    def get_subscription_count(self) -> int:
        return 1

    def publish(self, data) -> None:
        self.events.append(('publish', self.topic, time.monotonic()))

    def wait_for_all_acked(self, timeout) -> bool:
        self.events.append(('wait', self.topic, timeout.nanoseconds * 1e-9))
        time.sleep(ACK_S)
        self.events.append(('acked', self.topic, time.monotonic()))
        return True


class Node:
    def __init__(self):
        self.events = []

    def create_publisher(self, msg_type, topic: str, qos) -> Publisher:
        return Publisher(topic, self.events)


@pytest.fixture
def recording(tmp_path):
    """/y (volatile) and /plant_info (latched), each message SPACING_S after the last:
    /y, /y, /plant_info, /y, /y."""
    from metampc_msgs.msg import PlantInfo, PlantOutput
    from rclpy.serialization import serialize_message
    path = tmp_path / 'two_topics.mcap'
    writer = Rosbag2McapWriter(McapWriterConfig(str(path)))
    writer.add_topic('/y', 'metampc_msgs/msg/PlantOutput', [QosProfile()])
    writer.add_topic('/plant_info', 'metampc_msgs/msg/PlantInfo',
                     [QosProfile(durability='transient_local', depth=1)])
    t0 = 1_700_000_000_000_000_000
    for k, topic in enumerate(['/y', '/y', '/plant_info', '/y', '/y']):
        msg = PlantOutput(step=k) if topic == '/y' else PlantInfo()
        writer.write(topic, serialize_message(msg), t0 + round(k * SPACING_S * 1e9), t0)
    writer.close()
    return read_recording(str(path), messages=False)


def test_a_volatile_topic_goes_on_only_once_its_first_message_is_acknowledged(recording):
    node = Node()
    counts = play(recording, node, PlayConfig(wait_for_subscribers=7.0, ack_timeout=0.0))
    assert counts == {'/y': 4, '/plant_info': 1}
    during = node.events[:-4]       # the last: each publisher's wait at the end of the play
    assert [e[:2] for e in during] == [
        ('publish', '/y'), ('wait', '/y'), ('acked', '/y'), ('publish', '/y'),
        ('publish', '/plant_info'), ('publish', '/y'), ('publish', '/y')]
    assert during[1][2] == pytest.approx(7.0)
    # The playback's clock waited with it: the recorded spacing holds after the pause.
    times = [e[2] for e in during if e[0] == 'publish']
    assert times[1] - during[2][2] == pytest.approx(SPACING_S, abs=0.03)
    assert times[-1] - times[1] == pytest.approx(3 * SPACING_S, abs=0.03)


def test_without_the_wait_nothing_waits_for_acknowledgements(recording):
    node = Node()
    play(recording, node, PlayConfig(ack_timeout=0.0))
    assert [e[0] for e in node.events[:5]] == ['publish'] * 5
