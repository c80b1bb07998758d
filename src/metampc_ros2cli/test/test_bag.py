"""`ros2 bag record|info|play` as a user runs them: the `ros2` command, in subprocesses.

A realtime plant is recorded with `ros2 bag record` (stopped with SIGINT, as Ctrl-C); what
`ros2 bag info` prints of the bag folder and of its MCAP file is checked against rosbags, an
independent reader (counts per topic and in all, types, first and last log time, sizes), and
what `ros2 bag play` publishes against what a probe subscription receives. rosbag2's own test
bags check the printing against what rosbag2's end-to-end test expects of them. Errors are one
line and a non-zero status.
"""
from dataclasses import dataclass
import datetime
import os
from pathlib import Path
import re
import subprocess
from typing import Dict, List

from metampc_recording.recording_reader import read_recording
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosbags.highlevel import AnyReader
import yaml

BAGS = Path(__file__).parent / 'rosbag2_bags'     # written by rosbag2 (see its README.md)
STREAM = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
RECORDED_Y = 60     # /y samples the recording holds at least (50 Hz plant)


def ros2(*args, cwd=None, timeout=60) -> subprocess.CompletedProcess:
    """`ros2 ARGS` run to its end."""
    return subprocess.run(['ros2', *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


def start(group, *args) -> subprocess.Popen:
    """`ros2 ARGS` in a session of its own (SIGINT reaches it as Ctrl-C does), its output in a
    log file; `group` (a ProcessGroup) stops it if the test does not."""
    log_path = os.path.join(group.log_dir, f'ros2-{len(group.procs)}.log')
    with open(log_path, 'w') as log:
        proc = subprocess.Popen(['ros2', *map(str, args)], stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True,
                                env={**os.environ, 'PYTHONUNBUFFERED': '1'})
    proc.log_path = log_path
    group.procs.append(proc)
    return proc


@dataclass
class Recorded:
    """A bag folder `ros2 bag record` made of a realtime plant, as rosbags reads it.

    Attributes:
        folder, file: the bag folder and its MCAP file. log: what `ros2 bag record` printed.
        topics: topic -> type, in the reader's order. counts: topic -> messages iterated.
        times: log times of every message, ns. steps: the `step` of every /y, in order.
        y_times: their log times.
    """

    folder: Path
    file: Path
    log: str
    topics: Dict[str, str]
    counts: Dict[str, int]
    times: List[int]
    steps: List[int]
    y_times: List[int]


def read_with_rosbags(path: Path) -> Recorded:
    """`path` (bag folder or MCAP file) as rosbags reads it: its own parsing, message by
    message."""
    counts: Dict[str, int] = {}
    times, steps, y_times = [], [], []
    with AnyReader([path]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        for connection, t, raw in reader.messages():
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
            times.append(t)
            if connection.topic == '/y':
                steps.append(reader.deserialize(raw, connection.msgtype).step)
                y_times.append(t)
    return Recorded(path, path, '', topics, counts, times, steps, y_times)


@pytest.fixture(scope='module')
def recorded(tmp_path_factory) -> Recorded:
    """`ros2 bag record -o FOLDER /y /plant_info` of a 50 Hz realtime plant, stopped with
    SIGINT once the file holds RECORDED_Y samples; the plant is stopped after it."""
    from metampc_testing import ProcessGroup, TestNode
    base = tmp_path_factory.mktemp('bag')
    group = ProcessGroup(str(base))
    probe = TestNode('bag_record_probe')
    folder = base / 'plant_run'
    file = folder / 'plant_run_0.mcap'
    try:
        plant = group.start('metampc_plant', 'plant',
                            params={'mode': 'realtime', 'rate_hz': 50.0}, name='plant')
        recorder = start(group, 'bag', 'record', '-o', folder, '/y', '/plant_info')

        def subscribed(topic):
            return any(i.node_name == 'rosbag2_recorder'
                       for i in probe.node.get_subscriptions_info_by_topic(topic))
        probe.wait_for(lambda: subscribed('/y') and subscribed('/plant_info'), 60,
                       'the recorder to subscribe to /y and /plant_info')

        def samples():
            topic = read_recording(str(file)).topics.get('/y') if file.exists() else None
            return topic.count if topic else 0
        probe.wait_for(lambda: samples() >= RECORDED_Y, 60, f'{RECORDED_Y} samples recorded',
                       poll=0.2)
        assert group.interrupt(recorder) == 0, group.output(recorder)
        assert group.interrupt(plant) == 0, group.output(plant)
        log = group.output(recorder)
    finally:
        probe.close()
        group.stop_all()
    bag = read_with_rosbags(folder)
    bag.file, bag.log = file, log
    return bag


def test_record_makes_a_rosbag2_folder_with_the_recorders_file(recorded):
    assert sorted(p.name for p in recorded.folder.iterdir()) == ['metadata.yaml',
                                                                 'plant_run_0.mcap']
    assert recorded.topics == {'/plant_info': 'metampc_msgs/msg/PlantInfo',
                               '/y': 'metampc_msgs/msg/PlantOutput'}
    assert recorded.counts['/plant_info'] == 1 and recorded.counts['/y'] >= RECORDED_Y
    # consecutive plant steps: nothing lost between the first and the last sample recorded
    assert recorded.steps == list(range(recorded.steps[0], recorded.steps[0] + len(
        recorded.steps)))
    assert f'wrote {sum(recorded.counts.values())} messages on 2 topics' in recorded.log
    # The recorder's own file (its library, its run metadata record), and metadata.yaml is the
    # bag metadata it stored in it on closing; rosbags reads both the same.
    read = read_recording(str(recorded.file))
    assert read.complete and 'metampc' in read.metadata
    with open(recorded.file, 'rb') as f:
        assert b'metampc_recorder' in f.read(200)
    stored = yaml.safe_load(read.metadata['rosbag2']['serialized_metadata'])
    meta = yaml.safe_load((recorded.folder / 'metadata.yaml').read_text())
    assert meta == {'rosbag2_bagfile_information': stored}
    assert stored['message_count'] == len(recorded.times)
    assert read_with_rosbags(recorded.file).counts == recorded.counts


def _expected_info(files: str, size: int, bag: Recorded) -> str:
    """What rosbag2 prints for `bag`, from rosbags' numbers (rosbag2's format_bag_meta_data
    rules: local time, ns as 9 digits, sizes in KiB with one decimal)."""
    start, end = min(bag.times), max(bag.times)

    def when(ns):
        seconds, rest = divmod(ns, 10 ** 9)
        local = datetime.datetime.fromtimestamp(seconds)
        return f'{local:%b %e %Y %H:%M:%S}.{rest:09d} ({seconds}.{rest:09d})'
    topics = [f'Topic: {t} | Type: {kind} | Count: {bag.counts[t]} | Serialization Format: cdr'
              for t, kind in bag.topics.items()]
    return ('\n'
            f'Files:             {files}\n'
            f'Bag size:          {size / 1024:.1f} KiB\n'
            'Storage id:        mcap\n'
            'ROS Distro:        jazzy\n'
            f'Duration:          {(end - start) // 10 ** 9}.{(end - start) % 10 ** 9:09d}s\n'
            f'Start:             {when(start)}\n'
            f'End:               {when(end)}\n'
            f'Messages:          {len(bag.times)}\n'
            'Topic information: ' + ('\n' + ' ' * 19).join(topics) + '\n'
            'Service:           0\n'
            'Service information: \n')


def test_info_of_the_folder_and_of_the_file_equals_rosbags(recorded):
    folder_size = sum(p.stat().st_size for p in recorded.folder.iterdir())
    r = ros2('bag', 'info', recorded.folder)
    assert (r.returncode, r.stderr) == (0, '')
    assert r.stdout == _expected_info('plant_run_0.mcap', folder_size, recorded)

    by_file = read_with_rosbags(recorded.file)    # its own reading of the MCAP file
    r = ros2('bag', 'info', recorded.file)
    assert (r.returncode, r.stderr) == (0, '')
    assert r.stdout == _expected_info(str(recorded.file), recorded.file.stat().st_size,
                                      by_file)

    r = ros2('bag', 'info', '-t', recorded.folder)
    assert r.stdout.splitlines() == list(recorded.topics)


def test_info_prints_what_rosbag2_prints_of_its_own_bags():
    # rosbag2's test_rosbag2_info_end_to_end.cpp: its regular expressions and substrings,
    # run as it runs them (in the resources folder; the time zone is not asserted).
    r = ros2('bag', 'info', 'cdr_test', cwd=BAGS)
    assert r.returncode == 0, r.stderr
    assert re.search('\nFiles:             cdr_test_0.mcap'
                     '\nBag size:          .*B'
                     '\nStorage id:        mcap'
                     '\nROS Distro:        unknown'
                     '\nDuration:          0.151137181s'
                     '\nStart:             Apr  .+ 2020 .*:.*:36.763032325 '
                     r'\(1586406456.763032325\)'
                     '\nEnd:               Apr  .+ 2020 .*:.*:36.914169506 '
                     r'\(1586406456.914169506\)'
                     '\nMessages:          7'
                     '\nTopic information: ', r.stdout), r.stdout
    assert ('Topic: /test_topic | Type: test_msgs/msg/BasicTypes | Count: 3 | '
            'Serialization Format: cdr\n') in r.stdout
    assert ('Topic: /array_topic | Type: test_msgs/msg/Arrays | Count: 4 | '
            'Serialization Format: cdr') in r.stdout

    head = ('\nFiles:             bag_with_topics_and_service_events.mcap'
            '\nBag size:          .*B'
            '\nStorage id:        mcap'
            '\nROS Distro:        unknown'
            '\nDuration:          0\\.0706.*s'
            '\nStart:             Nov  7 2023 .*:30:36\\..* \\(1699345836\\..*\\)'
            '\nEnd:               Nov  7 2023 .*:30:36\\..* \\(1699345836\\..*\\)'
            '\nMessages:          2'
            '\nTopic information: ')
    r = ros2('bag', 'info', 'bag_with_topics_and_service_events', '--verbose', '--topic-name',
             cwd=BAGS)
    assert r.returncode == 0, r.stderr
    assert ("Warning! You have set both the '-t' and '-v' parameters. The '-t' parameter "
            'will be ignored.\n') in r.stdout
    assert re.search(head, r.stdout) and 'Service:           2\n' in r.stdout, r.stdout

    r = ros2('bag', 'info', 'bag_with_topics_and_service_events', '--verbose', cwd=BAGS)
    assert r.returncode == 0 and re.search(head, r.stdout), r.stdout
    for line in ('Topic: /events/write_split | Type: rosbag2_interfaces/msg/WriteSplitEvent | '
                 'Count: 0 | Serialization Format: cdr\n',
                 'Topic: /test_topic1 | Type: test_msgs/msg/Strings | Count: 1 | '
                 'Serialization Format: cdr\n',
                 'Topic: /test_topic2 | Type: test_msgs/msg/Strings | Count: 1 | '
                 'Serialization Format: cdr\n',
                 'Service:           2\n',
                 'Service: /test_service1 | Type: test_msgs/srv/BasicTypes | Request Count: 2 | '
                 'Response Count: 2 | Serialization Format: cdr\n',
                 'Service: /test_service2 | Type: test_msgs/srv/BasicTypes | Request Count: 2 | '
                 'Response Count: 2 | Serialization Format: cdr\n'):
        assert line in r.stdout, line
    # Without -v, the event counts (rosbag2's format_service_with_type; its metadata.yaml).
    r = ros2('bag', 'info', 'bag_with_topics_and_service_events', cwd=BAGS)
    assert r.stdout.endswith(
        'Service:           2\n'
        'Service information: Service: /test_service1 | Type: test_msgs/srv/BasicTypes | '
        'Event Count: 4 | Serialization Format: cdr\n'
        '                     Service: /test_service2 | Type: test_msgs/srv/BasicTypes | '
        'Event Count: 4 | Serialization Format: cdr\n\n'), r.stdout

    r = ros2('bag', 'info', 'does_not_exist', cwd=BAGS)
    assert r.returncode != 0 and "'does_not_exist' does not exist" in r.stderr
    r = ros2('bag', 'info', BAGS)     # a folder of bags, no metadata.yaml
    assert r.returncode == 1 and 'Could not find metadata' in r.stderr


def test_play_publishes_the_recorded_messages(recorded, procs, probe):
    got = {'/y': [], '/plant_info': []}
    probe.node.create_subscription(type_of('/y'), '/y', got['/y'].append, STREAM)
    probe.node.create_subscription(type_of('/plant_info'), '/plant_info',
                                   got['/plant_info'].append, LATCHED)
    # --wait-subscribers: a volatile sample sent before the player matched the probe would be
    # lost for it (as with rosbag2's player).
    player = start(procs, 'bag', 'play', recorded.folder, '--wait-subscribers', '30')
    assert player.wait(90) == 0, procs.output(player)
    probe.wait_for(lambda: len(got['/y']) >= len(recorded.steps) and got['/plant_info'], 30,
                   'the played messages')
    assert [m.step for m in got['/y']] == recorded.steps
    assert len(got['/plant_info']) == 1


def test_play_loops_from_the_start_offset_until_ctrl_c(recorded, procs, probe):
    offset = 0.5    # s
    first = recorded.y_times[0] + int(offset * 1e9)
    expected = [s for s, t in zip(recorded.steps, recorded.y_times) if t >= first]
    got = []
    probe.node.create_subscription(type_of('/y'), '/y', got.append, STREAM)
    player = start(procs, 'bag', 'play', recorded.file, '--topics', '/y', '--loop',
                   '--start-offset', offset, '--rate', '2', '--wait-subscribers', '30')
    probe.wait_for(lambda: len(got) > 2 * len(expected), 90, 'two passes of the loop')
    assert procs.interrupt(player) == 0, procs.output(player)
    steps = [m.step for m in got]
    assert steps[:2 * len(expected)] == expected * 2
    assert 'Traceback' not in procs.output(player)


def type_of(topic: str):
    from metampc_msgs.msg import PlantInfo, PlantOutput
    return {'/y': PlantOutput, '/plant_info': PlantInfo}[topic]


def test_unfinished_file_is_counted_through_and_a_cut_one_refused(tmp_path):
    """A file without summary (a recorder killed after its last chunk) is read record by
    record, with a warning; one that ends inside a record is an error, as in rosbag2."""
    from metampc_recording.mcap_writer import McapWriterConfig, Rosbag2McapWriter
    from metampc_recording.rosbag2_qos import QosProfile
    from metampc_msgs.msg import ControlInput, PlantOutput
    from rclpy.serialization import serialize_message
    whole = tmp_path / 'whole.mcap'
    writer = Rosbag2McapWriter(McapWriterConfig(str(whole), chunk_size=512))
    writer.add_topic('/y', 'metampc_msgs/msg/PlantOutput', [QosProfile()])
    writer.add_topic('/u', 'metampc_msgs/msg/ControlInput', [QosProfile()])
    t0 = 1_700_000_000_123_456_789
    for k in range(30):
        writer.write('/y', serialize_message(PlantOutput(step=k, y=[0.1 * k])),
                     t0 + k * 10_000_000, t0)
        if k % 3 == 0:
            writer.write('/u', serialize_message(ControlInput(step=k, u=[0.0])),
                         t0 + k * 10_000_000 + 1, t0)
    writer.flush()
    unfinished = tmp_path / 'unfinished.mcap'
    unfinished.write_bytes(whole.read_bytes())      # every chunk, no summary, no footer
    writer.close()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(unfinished.read_bytes()[:-5])   # ends inside its last record

    finished = ros2('bag', 'info', whole)
    r = ros2('bag', 'info', unfinished)
    assert r.returncode == 0
    assert r.stderr.strip().splitlines() == [
        f'[WARN] [ros2bag]: {unfinished} has no summary (an unfinished recording): its '
        'complete records were counted']
    # The same as the summary of the finished file says, but for the file's name and size.
    assert r.stdout.splitlines()[3:] == finished.stdout.splitlines()[3:]
    assert 'Messages:          40\n' in r.stdout
    assert 'Duration:          0.290000000s\n' in r.stdout
    assert '(1700000000.123456789)\nEnd:' in r.stdout
    assert 'Topic: /u | Type: metampc_msgs/msg/ControlInput | Count: 10 |' in r.stdout

    for verb in ('info', 'play'):
        r = ros2('bag', verb, cut)
        assert r.returncode == 1 and r.stdout == ''
        assert r.stderr.strip().splitlines() == [
            f'{cut} is cut short: its record at byte {cut_at(unfinished)} runs past the end '
            f'of the file ({cut.stat().st_size} bytes)'], r.stderr


def cut_at(path: Path) -> int:
    """Where the last record of MCAP file `path` (which ends where a record ends) starts, by
    mcap's stream reader: the file position after the record before it."""
    from mcap.exceptions import EndOfFile
    from mcap.stream_reader import StreamReader
    ends = []
    with open(path, 'rb') as f:
        try:
            for _ in StreamReader(f, emit_chunks=True).records:
                ends.append(f.tell())
        except EndOfFile:     # no footer
            pass
    assert ends[-1] == path.stat().st_size
    return ends[-2]


def test_errors_are_one_line_and_a_non_zero_status(recorded, tmp_path):
    text = tmp_path / 'notes.md'
    text.write_text('# not a bag\n')
    bad = tmp_path / 'bad_bag'
    bad.mkdir()
    (bad / 'metadata.yaml').write_text('rosbag2_bagfile_information: [1\n')
    cases = [
        (('bag', 'info', tmp_path / 'nothing'), 2,
         f"ros2 bag info: error: argument bag_path: Bag path '{tmp_path / 'nothing'}' does "
         'not exist!'),
        (('bag', 'info', text), 1, f'No plugin detected that could open file {text}'),
        (('bag', 'play', text), 1, f'No plugin detected that could open file {text}'),
        (('bag', 'info', bad), 1, f'Exception on parsing info file: {bad}/metadata.yaml'),
        (('bag', 'play', recorded.folder, '--topics', '/nope'), 1,
         'not in the recording: /nope'),
        (('bag', 'play', recorded.folder, '--rate', '0'), 2,
         'ros2 bag play: error: argument -r/--rate: 0 is not in the valid range (> 0.0)'),
        (('bag', 'record', '-o', recorded.folder, '-a'), 1,
         f"[ERROR] [ros2bag]: Output folder '{recorded.folder}' already exists."),
        (('bag', 'record', '-o', tmp_path / 'none'), 1,
         '[ERROR] [ros2bag]: Need to specify at least one option out of --all, --all-topics '
         'or --topics'),
        (('bag', 'record', '-o', tmp_path / 'bad_name', '/bad name'), 2,
         'invalid parameter: bad topic name in topics'),
        (('bag', 'record', '-o', tmp_path / 'bad_node', '-a', '--node-name', 'a b'), 1,
         "[ERROR] [ros2bag]: Invalid node name: node name must not contain characters other "
         "than alphanumerics or '_': 'a b'"),
    ]
    for args, status, says in cases:
        r = ros2(*args)
        assert (r.returncode, r.stdout) == (status, ''), (args, r.stderr)
        lines = r.stderr.strip().splitlines()
        if not r.stderr.startswith('usage:'):     # argparse's: its usage, then the error line
            assert len(lines) == 1, (args, lines)
        assert says in lines[-1], (args, lines)
    assert not any((tmp_path / name).exists() for name in ('bad_name', 'bad_node', 'none'))
