"""The recorder node as a real process: what it writes, how it stops, how it fails.

Independent readers (rosbags, and mcap's own summary) check the files: a lockstep run of the
real plant (the session's `closed_loop` recording), and streams the probe node publishes.
"""
import array
import json
import math
import os
import signal
import time

from mcap.reader import make_reader
from metampc_recording.msg_schema import DefinitionSource
from metampc_recording.recording_reader import read_recording
from metampc_common.held_publisher import held_qos, HeldPublisher, HoldConfig
from metampc_recording.rosbag2_qos import profiles_from_yaml
from metampc_msgs.msg import PlantOutput
from metampc_testing import own_lines
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.highlevel import AnyReader
import yaml

# One xdist worker runs this file and test_run_report.py: they share the session's recorded
# closed-loop run (recording_fixtures.closed_loop), built once.
pytestmark = pytest.mark.xdist_group('closed_loop')

STREAM = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED_TOPICS = ('/plant_info', '/nssm_weights')


def same(ros_msg, other, where=''):
    """Field-by-field equality of an rclpy message and a decoded one (rosbags or mcap_ros2);
    NaN equals NaN."""
    for name in ros_msg.get_fields_and_field_types():
        a, b = getattr(ros_msg, name), getattr(other, name)
        if hasattr(a, 'get_fields_and_field_types'):
            same(a, b, f'{where}.{name}')
        elif isinstance(a, (list, tuple, array.array, np.ndarray)):
            assert list(a) == list(b), f'{where}.{name}: {list(a)} != {list(b)}'
        elif isinstance(a, float) and math.isnan(a):
            assert math.isnan(b), f'{where}.{name}: {b} is not NaN'
        else:
            assert a == b, f'{where}.{name}: {a!r} != {b!r}'


def output_msg(k, episode=0):
    msg = PlantOutput(step=k, y=[np.sin(0.1 * k) + episode, np.cos(0.1 * k)],
                      u_applied=[0.1 * (k % 5)], saturated=k % 6 == 0, diverged=False)
    msg.header.stamp.sec, msg.header.stamp.nanosec = k // 10, (k % 10) * 100_000_000
    return msg


def test_rosbags_reads_the_lockstep_plant_run_as_it_was_published(closed_loop):
    published = closed_loop.published
    counts = {topic: len(msgs) for topic, msgs in published.items()}
    assert counts['/y'] == 60 and counts['/clock'] == 60 and counts['/plant_info'] == 2
    definitions = DefinitionSource()
    # No default typestore: every type, metampc_msgs included, comes from the schema text
    # embedded in the file (rosbag2's complete definition: the file and its dependencies).
    with AnyReader([closed_loop.path]) as reader:
        assert {c.topic: c.msgcount for c in reader.connections} == counts
        assert {c.topic: c.msgtype for c in reader.connections} == closed_loop.types
        decoded = {topic: [] for topic in counts}
        for connection, _, raw in reader.messages():
            decoded[connection.topic].append(reader.deserialize(raw, connection.msgtype))
        for connection in reader.connections:
            assert connection.ext.serialization_format == 'cdr'
            assert connection.msgdef.data == definitions.get(connection.msgtype).text
            offered = connection.ext.offered_qos_profiles
            assert len(offered) == 1, connection.topic    # one publisher per topic
            assert offered[0].reliability.name == 'RELIABLE'
            latched = connection.topic in LATCHED_TOPICS
            assert offered[0].durability.name == ('TRANSIENT_LOCAL' if latched else 'VOLATILE')
    for topic, msgs in published.items():
        for i, (sent, got) in enumerate(zip(msgs, decoded[topic], strict=True)):
            same(sent, got, f'{topic}[{i}]')

    with open(closed_loop.path, 'rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        stats = {summary.channels[c].topic: n
                 for c, n in summary.statistics.channel_message_counts.items()}
        assert stats == counts
        assert summary.statistics.message_count == sum(counts.values())
        assert summary.statistics.chunk_count > 1
        assert {i.compression for i in summary.chunk_indexes} == {'zstd'}
        for channel in summary.channels.values():
            offered = channel.metadata['offered_qos_profiles']
            assert isinstance(yaml.safe_load(offered), list)
            assert len(profiles_from_yaml(offered)) == 1
            assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
            assert summary.schemas[channel.schema_id].encoding == 'ros2msg'
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert json.loads(metadata['metampc']['config']) == closed_loop.run_config
    bag = yaml.safe_load(metadata['rosbag2']['serialized_metadata'])
    assert bag['message_count'] == sum(counts.values())
    assert {t['topic_metadata']['name']: t['message_count']
            for t in bag['topics_with_message_count']} == counts


def test_sigkill_mid_run_leaves_every_complete_chunk_readable(
        tmp_path, procs, probe, recorders, complete_chunk_messages):
    path = tmp_path / 'killed.mcap'
    recorder = recorders.start(path, chunk_size=2048, flush_period=0.0)
    pub = probe.node.create_publisher(PlantOutput, 'y', STREAM)
    recorders.wait_matched([pub])
    sent = []

    def publish():
        sent.append(output_msg(len(sent)))
        pub.publish(sent[-1])
    timer = probe.node.create_timer(0.001, publish)
    recorders.wait_recorded(path, {'/y': 300})   # complete chunks only reach the disk
    procs.kill(recorder)                         # while the stream goes on
    probe.node.destroy_timer(timer)
    assert recorder.returncode != 0
    data = path.read_bytes()
    recording = read_recording(str(path))
    assert not recording.complete and recording.statistics is None
    got = [m for _, _, m in recording.decoded(['/y'])]
    # every complete chunk and nothing beyond it; whether a message was lost after the last
    # complete chunk depends on where the kill fell (a race), so it is not asserted
    assert len(got) == complete_chunk_messages(data) >= 300
    assert len(sent) >= len(got)
    for k, msg in enumerate(got):
        same(sent[k], msg, f'/y[{k}]')
    assert recording.run_config() == {}


def test_existing_output_is_an_error_and_left_alone(tmp_path, procs, recorders):
    path = tmp_path / 'taken.mcap'
    path.write_bytes(b'an earlier run')
    recorder = recorders.start(path)
    assert recorder.wait(30) == 2
    lines = own_lines(procs.output(recorder))
    assert len(lines) == 1 and 'exists' in lines[0] and str(path) in lines[0], lines
    assert path.read_bytes() == b'an earlier run'


def test_recorder_keeps_up_with_a_fast_stream_and_finishes_on_sigterm(
        tmp_path, procs, probe, recorders):
    rate_hz, n = 500, 1000
    path = tmp_path / 'fast.mcap'
    recorder = recorders.start(path, flush_period=0.2)
    pub = probe.node.create_publisher(PlantOutput, 'y', STREAM)
    recorders.wait_matched([pub])
    start = time.monotonic()
    for k in range(n):
        delay = start + k / rate_hz - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        pub.publish(output_msg(k))
    recorders.wait_recorded(path, {'/y': n})
    os.killpg(recorder.pid, signal.SIGTERM)
    assert recorder.wait(10) == 0, procs.output(recorder)
    assert f'wrote {n} messages on 1 topics' in procs.output(recorder)
    with open(path, 'rb') as f:
        statistics = make_reader(f).get_summary().statistics
    assert statistics.message_count == n
    assert read_recording(str(path)).complete


def test_a_held_stream_much_faster_than_the_recorder_is_recorded_whole(
        tmp_path, procs, probe, recorders):
    """5000 outputs published as fast as Python can (some 20 times the recorder's pace)
    through a HeldPublisher: the recording holds every one. Writers that keep the last 1000,
    as before (hold_for_readers false), lose most of such a burst (docs/speed.md)."""
    n = 5000
    path = tmp_path / 'burst.mcap'
    recorder = recorders.start(path, flush_period=0.2)
    config = HoldConfig()
    pub = HeldPublisher(probe.node.create_publisher(PlantOutput, 'y', held_qos(config)), config)
    recorders.wait_matched([pub])
    assert all(pub.publish(output_msg(k)) for k in range(n))
    recorders.wait_recorded(path, {'/y': n})
    os.killpg(recorder.pid, signal.SIGTERM)
    assert recorder.wait(10) == 0, procs.output(recorder)
    with open(path, 'rb') as f:
        assert make_reader(f).get_summary().statistics.message_count == n
    assert pub.dropped == 0
