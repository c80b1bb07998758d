"""`ros2 node|topic|service|interface` against a live plant in the test's own ROS domain: each
output is checked against what the plant published or served, as a probe node saw it."""
import pathlib
import re
import signal
import subprocess
import threading

import pytest
import yaml
from metampc_msgs.msg import ControlInput, PlantInfo, PlantOutput
from metampc_msgs.srv import ResetPlant
from rclpy.qos import QoSDurabilityPolicy, QoSProfile, ReliabilityPolicy

from metampc_ros2cli import message_yaml

RATE_HZ = 20.0
# A listing shows what discovery found within --spin-time. With localhost-only discovery, as
# the tests run, a fresh participant often learns the others' endpoints only at their next
# announcement (~3 s; docs/nodes.md); a user's default (subnet) discovery takes ~0.2 s.
LIST = ('--spin-time', '4')
MSG_DIR = pathlib.Path(__file__).resolve().parents[2] / 'metampc_msgs' / 'msg'


def ros2(*args, timeout=60.0, **kwargs):
    return subprocess.run(['ros2', *args], capture_output=True, text=True, timeout=timeout,
                          **kwargs)


class Recorder:
    """What the probe receives on one topic."""

    def __init__(self, probe, cls, topic, qos=10):
        self.msgs, self.lock = [], threading.Lock()
        probe.node.create_subscription(cls, topic, self.add, qos)

    def add(self, msg):
        with self.lock:
            self.msgs.append(msg)

    def snapshot(self):
        with self.lock:
            return list(self.msgs)


def _listed(verb: str) -> set:
    out = ros2(verb, 'list')
    return set(out.stdout.split()) if out.returncode == 0 else set()


@pytest.fixture(scope='module')
def graph(tmp_path_factory):
    """One realtime plant at RATE_HZ for the module (each test starting its own would add ~5 s
    per test); the probe records its y. The list verbs answer from a daemon started here and
    waited for until it lists the plant's endpoints: a verb's own node (or a daemon just
    started by it) under localhost discovery may miss some (once in CI: /u), and completeness
    is test_daemon's subject, not this file's. Stopped, with the daemon and the probe, after
    the last test."""
    from metampc_testing import ProcessGroup, TestNode
    group = ProcessGroup(str(tmp_path_factory.mktemp('graph_verbs')))
    probe = TestNode()
    ros2('daemon', 'stop')
    try:
        group.start('metampc_plant', 'plant', params={'mode': 'realtime', 'rate_hz': RATE_HZ})
        ys = Recorder(probe, PlantOutput, 'y')
        probe.wait_for(lambda: len(ys.snapshot()) > 3, 60.0, 'y from the plant')
        assert ros2('daemon', 'start').returncode == 0
        probe.wait_for(lambda: {'/y', '/u', '/plant_info'} <= _listed('topic')
                       and '/reset' in _listed('service') and '/plant' in _listed('node'),
                       60.0, "the plant's endpoints in the daemon's listings")
        yield ys, probe
    finally:
        ros2('daemon', 'stop')
        probe.close()
        group.stop_all()


@pytest.fixture
def plant(graph):
    """The module's plant is still running (a test's error cannot hide a crash of it)."""
    ys, probe = graph
    count = len(ys.snapshot())
    probe.wait_for(lambda: len(ys.snapshot()) > count, 30.0, 'y still coming')
    return ys


@pytest.fixture
def probe(graph):
    return graph[1]


def test_topic_list_and_info_match_the_graph(plant, probe):
    out = ros2('topic', 'list', '-t', *LIST)
    assert out.returncode == 0, out
    listed = dict(re.fullmatch(r'(\S+) \[(.+)\]', line).groups()
                  for line in out.stdout.splitlines())
    graph = {n: ', '.join(t) for n, t in probe.node.get_topic_names_and_types()}
    assert listed['/y'] == 'metampc_msgs/msg/PlantOutput'
    assert {k: graph[k] for k in ('/y', '/u', '/plant_info')} == {
        k: listed[k] for k in ('/y', '/u', '/plant_info')}

    info = ros2('topic', 'info', '/y', *LIST)
    assert info.returncode == 0, info
    assert info.stdout.splitlines() == [
        'Type: metampc_msgs/msg/PlantOutput',
        f"Publisher count: {probe.node.count_publishers('/y')}",
        f"Subscription count: {probe.node.count_subscribers('/y')}"]
    assert ros2('topic', 'type', '/y').stdout == 'metampc_msgs/msg/PlantOutput\n'
    assert '/y' in ros2('topic', 'find', 'metampc_msgs/msg/PlantOutput', *LIST).stdout.split()


def test_node_list_and_info_match_the_graph(plant, probe):
    out = ros2('node', 'list', *LIST)
    assert out.returncode == 0 and '/plant' in out.stdout.split(), out
    info = ros2('node', 'info', '/plant', *LIST)
    assert info.returncode == 0, info
    lines = info.stdout.splitlines()
    assert lines[0] == '/plant' and lines[1] == '  Subscribers:'
    sections = {}
    current = None
    for line in lines[1:]:
        if line.startswith('  ') and not line.startswith('    '):
            current = sections.setdefault(line.strip().rstrip(':'), [])
        elif line:
            current.append(line.strip())
    node = probe.node
    for title, query in (('Publishers', node.get_publisher_names_and_types_by_node),
                         ('Subscribers', node.get_subscriber_names_and_types_by_node),
                         ('Service Servers', node.get_service_names_and_types_by_node)):
        expected = [f'{n}: {", ".join(t)}' for n, t in query('plant', '/')]
        assert sections[title] == expected
    assert '/y: metampc_msgs/msg/PlantOutput' in sections['Publishers']
    assert '/reset: metampc_msgs/srv/ResetPlant' in sections['Service Servers']
    missing = ros2('node', 'info', '/nope', '--spin-time', '0.1')
    assert missing.returncode == 1 and missing.stderr == "Unable to find node '/nope'\n"


def test_topic_echo_once_parses_back_to_the_message_the_probe_received(plant):
    ys = plant
    out = ros2('topic', 'echo', '/y', '--once')
    assert out.returncode == 0, out
    assert out.stdout.endswith('---\n')
    printed = yaml.safe_load(out.stdout[:-len('---\n')])
    msg = message_yaml.from_yaml(PlantOutput, out.stdout[:-len('---\n')])
    same = [m for m in ys.snapshot() if m.step == printed['step']]
    assert msg in same      # (a reset by another test restarts the steps)
    field = ros2('topic', 'echo', '/plant_info', '--once', '--field', 'family')
    assert field.stdout == 'vanderpol\n---\n', field
    csv = ros2('topic', 'echo', '/y', '--once', '--csv')
    assert csv.stdout.count(',') == len(message_yaml.to_csv(msg).split(',')) - 1, csv


def _lines_until(proc, count, pattern):
    """The first `count` stdout lines of a running verb matching `pattern`, then SIGINT."""
    found = []
    for line in proc.stdout:
        if re.search(pattern, line):
            found.append(line)
            if len(found) == count:
                break
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=30)
    return found


def test_topic_hz_is_the_plants_rate_and_ctrl_c_exits_0(plant):
    proc = subprocess.Popen(['ros2', 'topic', 'hz', '/y'], stdout=subprocess.PIPE, text=True)
    try:
        lines = _lines_until(proc, 5, r'^average rate: ')
    finally:
        if proc.poll() is None:
            proc.kill()
    rates = [float(line.split()[2]) for line in lines]
    # The rate is (messages - 1) / (last - first reception time) since the start, so only the
    # delivery delay of the first and the newest message moves it: on a loaded CI machine the
    # first report (about 1 s) read 21.6 Hz. The fifth covers about 5 s; 10 % there is a
    # 0.5 s delay, and the plant's rate halved or doubled fails every report.
    assert all(abs(r / RATE_HZ - 1) < 0.25 for r in rates), rates
    assert abs(rates[-1] / RATE_HZ - 1) < 0.1, rates
    assert proc.returncode == 0


def test_topic_bw_counts_the_serialized_size(plant):
    from rclpy.serialization import serialize_message
    size = len(serialize_message(plant.snapshot()[-1]))
    proc = subprocess.Popen(['ros2', 'topic', 'bw', '/y'], stdout=subprocess.PIPE, text=True)
    try:
        lines = _lines_until(proc, 2, r'Message size mean')
    finally:
        if proc.poll() is None:
            proc.kill()
    kb = f'{size / 1000:.2f} KB'     # 20 Hz x ~70 B: over 1000 B/s, so kilobytes
    assert f'mean: {kb} min: {kb} max: {kb}' in lines[-1], lines


def test_topic_pub_reaches_a_subscriber_and_bad_input_is_one_line(plant, probe):
    got = Recorder(probe, ControlInput, 'u')
    # -w 2: the plant's and the probe's subscriptions (a volatile message published before
    # the probe has matched would never reach it)
    out = ros2('topic', 'pub', '/u', 'metampc_msgs/msg/ControlInput',
               '{step: 3, u: [0.25], model_version: 2}', '--once', '-w', '2')
    assert out.returncode == 0, out
    assert re.fullmatch(r'(Waiting for at least 2 matching subscription\(s\)\.\.\.\n)?'
                        r'publisher: beginning loop\npublishing #1: metampc_msgs\.msg\.'
                        r'ControlInput\(.*\)\n\n', out.stdout), out
    probe.wait_for(lambda: got.snapshot(), 30.0, 'the published input')
    assert got.snapshot()[0] == ControlInput(step=3, u=[0.25], model_version=2)
    for args, line in (
            (['metampc_msgs/msg/ControlInput', '{u: [0.2], nope: 1}'],
             "Failed to populate field: 'ControlInput' object has no attribute 'nope'"),
            (['metampc_msgs/msg/ControlInput', '{u: [0.2'],
             'The passed value is not valid YAML'),
            (['metampc_msgs/msg/Nope', '{}'], 'The passed message type is invalid')):
        bad = ros2('topic', 'pub', '/u', *args, '--once')
        assert bad.returncode == 1 and bad.stderr.startswith(line), bad
        assert bad.stderr.count('\n') == 1, bad


def test_service_list_and_call_reset_the_plant(plant, probe):
    out = ros2('service', 'list', '-t', *LIST)
    assert '/reset [metampc_msgs/srv/ResetPlant]' in out.stdout.splitlines(), out
    assert ros2('service', 'type', '/reset').stdout == 'metampc_msgs/srv/ResetPlant\n'
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=QoSDurabilityPolicy.TRANSIENT_LOCAL)
    infos = Recorder(probe, PlantInfo, 'plant_info', latched)
    probe.wait_for(lambda: infos.snapshot(), 30.0, 'plant_info')
    call = ros2('service', 'call', '/reset', 'metampc_msgs/srv/ResetPlant',
                '{theta: [0.3], x0: [0.5, -0.5]}')
    assert call.returncode == 0, call
    # ros2cli prints the waiting line only when discovery has not yet shown the server.
    reply = call.stdout.removeprefix('waiting for service to become available...\n')
    assert reply.startswith('requester: making request: '
                            f'{ResetPlant.Request(theta=[0.3], x0=[0.5, -0.5])!r}\n\n'
                            'response:\n'), call
    assert 'success=True' in call.stdout, call
    probe.wait_for(lambda: list(infos.snapshot()[-1].theta) == [0.3], 30.0,
                   'plant_info with the new theta')
    bad = ros2('service', 'call', '/reset', 'metampc_msgs/srv/ResetPlant', '{theta: [x]}')
    assert bad.returncode == 1
    assert bad.stderr == ("Failed to populate field: theta: expected a number (double), got "
                          "'x'\n")


def test_interface_show_is_the_file_with_nested_types_expanded():
    text = (MSG_DIR / 'ControlInput.msg').read_text()
    out = ros2('interface', 'show', 'metampc_msgs/msg/ControlInput')
    assert out.returncode == 0, out
    top = [line for line in out.stdout.splitlines() if not line.startswith('\t')]
    assert top == text.rstrip('\n').splitlines()
    assert '\tbuiltin_interfaces/Time stamp\n\t\tint32 sec\n\t\tuint32 nanosec\n' in out.stdout
    listed = ros2('interface', 'package', 'metampc_msgs').stdout.split()
    assert listed == sorted(f'metampc_msgs/msg/{p.stem}' for p in MSG_DIR.glob('*.msg')) + \
        sorted(f'metampc_msgs/srv/{p.stem}' for p in (MSG_DIR.parent / 'srv').glob('*.srv'))
    proto = ros2('interface', 'proto', 'metampc_msgs/msg/ControlInput', '--no-quotes')
    assert message_yaml.from_yaml(ControlInput, proto.stdout) == ControlInput()
    for name, line in (('metampc_msgs/msg/Nope', "Unknown interface 'metampc_msgs/msg/Nope'"),
                       ('nope/msg/X', "Unknown package 'nope'"),
                       ('a/b', "Invalid name 'a/b'. Expected three parts separated by '/'")):
        bad = ros2('interface', 'show', name)
        assert (bad.returncode, bad.stderr) == (1, line + '\n')


def test_no_verb_prints_the_help_and_an_unknown_verb_is_argparses_error():
    assert ros2().returncode == 0
    bad = ros2('topic', 'frobnicate')
    assert bad.returncode == 2 and 'invalid choice' in bad.stderr
