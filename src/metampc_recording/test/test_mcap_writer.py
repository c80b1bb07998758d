"""The MCAP writer core, checked with independent readers (rosbags, mcap) and no ROS graph."""
import importlib.util
import json
import os
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2._dynamic import serialize_dynamic
from metampc_recording.mcap_writer import McapWriterConfig, Rosbag2McapWriter
from metampc_recording.msg_schema import DefinitionSource
from metampc_recording.recording_reader import finished, read_recording
from metampc_recording.rosbag2_qos import profiles_from_yaml, QosProfile
import pytest
from rosbags.highlevel import AnyReader
import yaml

LATCHED = QosProfile(history='unknown', depth=0, durability='transient_local',
                     liveliness='automatic')
VOLATILE = QosProfile(history='unknown', depth=0, liveliness='automatic')


def _encoder(type_name):
    text = DefinitionSource().get(type_name).text
    return serialize_dynamic(type_name, text)[type_name]


def _output(k):
    return {'header': {'stamp': {'sec': k // 10, 'nanosec': (k % 10) * 100_000_000},
                       'frame_id': ''},
            'step': k, 'y': [0.1 * k, -0.2 * k], 'u_applied': [0.01 * k],
            'saturated': k % 7 == 0, 'diverged': False}


def _write_run(path, compression='lz4', chunk_size=1024, close=True):
    """30 PlantOutput on /y, 1 latched NssmWeights, 3 std_msgs/String; returns (writer, sent)."""
    config = McapWriterConfig(path, chunk_size, compression, {'seed': 3, 'tracked_outputs': [0]})
    writer = Rosbag2McapWriter(config)
    writer.add_topic('/nssm_weights', 'metampc_msgs/msg/NssmWeights', [LATCHED], 'RIHS01_ab')
    writer.add_topic('/y', 'metampc_msgs/msg/PlantOutput', [VOLATILE, VOLATILE], 'RIHS01_cd')
    writer.add_topic('/chatter', 'std_msgs/msg/String', [VOLATILE])
    weights = _encoder('metampc_msgs/msg/NssmWeights')
    outputs = _encoder('metampc_msgs/msg/PlantOutput')
    strings = _encoder('std_msgs/msg/String')
    sent = {'/nssm_weights': [{'version': 7, 'method': 'imaml', 'params': [0.5, -1.25]}],
            '/y': [_output(k) for k in range(30)],
            '/chatter': [{'data': f'hello {i}'} for i in range(3)]}
    t = 1_000_000_000
    writer.write('/nssm_weights', weights(sent['/nssm_weights'][0]), t, t - 5, 1)
    for k, msg in enumerate(sent['/y']):
        t += 1_000_000
        writer.write('/y', outputs(msg), t, t - 10, k + 1)
        if k % 10 == 0:
            writer.write('/chatter', strings(sent['/chatter'][k // 10]), t, t - 10, k // 10)
    if close:
        writer.close()
    return writer, sent


def test_independent_readers_agree_with_what_was_written(tmp_path):
    path = str(tmp_path / 'run.mcap')
    _write_run(path)
    with AnyReader([Path(path)]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts == {'/nssm_weights': 1, '/y': 30, '/chatter': 3}
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
        assert qos['/nssm_weights'][0].durability.name == 'TRANSIENT_LOCAL'
        assert len(qos['/y']) == 2
        got = {}
        for connection, _, raw in reader.messages():
            got.setdefault(connection.topic, []).append(
                reader.deserialize(raw, connection.msgtype))
    assert [m.step for m in got['/y']] == list(range(30))
    assert got['/y'][12].y.tolist() == [0.1 * 12, -0.2 * 12]
    assert [bool(m.saturated) for m in got['/y']] == [k % 7 == 0 for k in range(30)]
    assert got['/y'][13].header.stamp.nanosec == 300_000_000
    assert got['/nssm_weights'][0].params.tolist() == [0.5, -1.25]
    assert got['/nssm_weights'][0].method == 'imaml'
    assert [m.data for m in got['/chatter']] == ['hello 0', 'hello 1', 'hello 2']

    with open(path, 'rb') as f:
        reader = make_reader(f)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        channels = summary.channels
        for channel in channels.values():
            assert channel.message_encoding == 'cdr'
            parsed = yaml.safe_load(channel.metadata['offered_qos_profiles'])
            assert isinstance(parsed, list) and parsed
            assert profiles_from_yaml(channel.metadata['offered_qos_profiles'])
            assert summary.schemas[channel.schema_id].encoding == 'ros2msg'
        by_topic = {channels[cid].topic: n
                    for cid, n in summary.statistics.channel_message_counts.items()}
        assert by_topic == {'/nssm_weights': 1, '/y': 30, '/chatter': 3}
        assert summary.statistics.message_count == 34
        assert summary.statistics.chunk_count > 1
        metadata = {}
        for record in reader.iter_metadata():
            metadata[record.name] = record.metadata
    bag = yaml.safe_load(metadata['rosbag2']['serialized_metadata'])
    assert bag['version'] == 9 and bag['ros_distro'] == 'jazzy'
    assert bag['message_count'] == 34
    assert {t['topic_metadata']['name']: t['message_count']
            for t in bag['topics_with_message_count']} == by_topic
    assert json.loads(metadata['metampc']['config']) == {'seed': 3, 'tracked_outputs': [0]}


@pytest.mark.parametrize('compression', ['lz4', 'zstd', 'none'])
def test_compressions(tmp_path, compression):
    path = str(tmp_path / 'run.mcap')
    if compression == 'zstd' and importlib.util.find_spec('zstandard') is None:
        with pytest.raises(ValueError, match='zstandard'):
            _write_run(path, compression)
        assert not os.path.exists(path)
        return
    _write_run(path, compression)
    with AnyReader([Path(path)]) as reader:
        assert sum(1 for _ in reader.messages()) == 34


def test_existing_file_is_never_overwritten(tmp_path):
    path = tmp_path / 'run.mcap'
    path.write_bytes(b'precious')
    with pytest.raises(FileExistsError):
        _write_run(str(path))
    assert path.read_bytes() == b'precious'


@pytest.mark.parametrize('compression', ['lz4', 'none'])
def test_unfinished_file_reads_up_to_its_last_complete_chunk(tmp_path, compression,
                                                             complete_chunk_messages):
    path = str(tmp_path / 'run.mcap')
    writer, _ = _write_run(path, compression, chunk_size=512, close=False)
    # One more small message opens a chunk that cannot be complete yet, wherever the run's
    # last message put the chunk boundary (it moves with the message definitions' sizes).
    writer.write('/chatter', _encoder('std_msgs/msg/String')({'data': 'tail'}),
                 2_000_000_000, 2_000_000_000, 3)
    # What a SIGKILL would leave: the writer holds no user-space buffer, so this is the file.
    left = Path(path).read_bytes()
    in_chunks = complete_chunk_messages(left)
    assert 0 < in_chunks < 35
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(left)
    recording = read_recording(str(cut))
    assert not recording.complete and not finished(str(cut))
    assert len(recording.messages) == in_chunks
    steps = [m.step for _, _, m in recording.decoded(['/y'])]
    assert steps == list(range(len(steps)))
    assert recording.run_config() == {'seed': 3, 'tracked_outputs': [0]}
    # Cut anywhere: reading never fails and yields a prefix of the run.
    for size in range(len(left) // 2, len(left), 29):
        cut.write_bytes(left[:size])
        recording = read_recording(str(cut))
        steps = [m.step for _, _, m in recording.decoded(['/y'])]
        assert steps == list(range(len(steps)))
        assert not finished(str(cut))
    writer.close()
    recording = read_recording(path)
    assert recording.complete and len(recording.messages) == 35 and finished(path)
