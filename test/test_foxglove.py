"""The Foxglove live view (`ros2 run metampc_recording foxglove`) as Foxglove sees it.

A WebSocket client speaking the Foxglove protocol (metampc_recording.foxglove_client) connects to
the node, checks the advertised channels and their schemas, subscribes and decodes the CDR
payloads with rclpy; the probe subscribes to the plant directly and is the reference.
"""
import base64
import hashlib
import json
import os
import re
import socket
import struct
import time

from metampc_msgs.msg import PlantInfo, PlantOutput
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from websockets.exceptions import ConnectionClosed

from metampc_bringup.analysis.run_series import DEFAULT_TOPICS
from metampc_common.message_types import message_class
from metampc_recording.foxglove_client import FoxgloveClient
from metampc_recording.foxglove_server import LiveServer
from metampc_recording.msg_schema import (DefinitionSource, MessageDefinition,
                                          package_share_directory)
from metampc_testing import own_lines, session_pids

RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
PLANT_OUTPUT, PLANT_INFO = 'metampc_msgs/msg/PlantOutput', 'metampc_msgs/msg/PlantInfo'
TIMEOUT = 60.0      # s: generous, for a loaded 2-core machine
WS_PROTOCOL = 'foxglove.websocket.v1'   # what @foxglove/ws-protocol's client offers


def start_live_view(procs, probe, **params) -> tuple:
    """The node on a free port (port 0); returns (process, ws:// URL from its start-up line)."""
    proc = procs.start('metampc_recording', 'foxglove', params={'port': 0, **params})
    url = []

    def served() -> bool:
        url[:] = re.findall(r'serving (ws://127\.0\.0\.1:\d+)', procs.output(proc))
        assert proc.poll() is None, procs.output(proc)
        return bool(url)
    probe.wait_for(served, TIMEOUT, 'the live view to listen')
    return proc, url[0]


def stop_cleanly(procs, proc) -> None:
    code = procs.interrupt(proc)
    out = procs.output(proc)
    assert code == 0, out
    assert 'Traceback' not in out, out
    assert session_pids(proc) == [], 'a process of the node outlived ros2 run'


def test_client_gets_channels_with_schemas_and_the_plants_messages(procs, probe):
    """Started before the plant, the node advertises y and plant_info once they appear; y's
    payloads decode to exactly what the plant published; a second client that subscribes to
    the latched plant_info later gets it too."""
    ys, infos = {}, []
    probe.node.create_subscription(PlantOutput, 'y', lambda m: ys.setdefault(m.step, m),
                                   RELIABLE)
    probe.node.create_subscription(PlantInfo, 'plant_info', infos.append, LATCHED)
    live, url = start_live_view(procs, probe)
    with FoxgloveClient(url, TIMEOUT) as client:
        assert client.server_info['name'] == 'metampc /foxglove'
        assert client.server_info['sessionId']
        assert not [c for c in client.channels.values() if c['topic'] in ('/y', '/plant_info')]
        plant = procs.start('metampc_plant', 'plant', params={
            'mode': 'realtime', 'rate_hz': 50.0, 'x0': [1.0, 0.0], 'theta': 0.5,
            'measurement_noise_std': 0.01, 'seed': 3})
        definitions = DefinitionSource()
        channels = {}
        for topic, type_name in (('/y', PLANT_OUTPUT), ('/plant_info', PLANT_INFO)):
            channels[topic] = channel = client.channel(topic, TIMEOUT)
            assert (channel['schemaName'], channel['schemaEncoding'], channel['encoding']) == (
                type_name, 'ros2msg', 'cdr')
            assert channel['schema'] == definitions.get(type_name).text
            # The complete definition starts with the type's own .msg file, as installed.
            name = type_name.split('/')[-1]
            with open(os.path.join(package_share_directory('metampc_msgs'), 'msg',
                                   f'{name}.msg')) as f:
                assert channel['schema'].startswith(f.read())
        assert 'MSG: std_msgs/Header' in channels['/y']['schema']
        # The probe must hold every sample the client gets: it receives from the plant from
        # its first sample on (reliable), so the client subscribes only after that.
        probe.wait_for(lambda: ys, TIMEOUT, "the probe's first sample")
        client.subscribe(channels['/y'])
        client.subscribe(channels['/plant_info'])
        got = {'/y': [], '/plant_info': []}
        while len(got['/y']) < 50 or not got['/plant_info']:
            msg = client.message(TIMEOUT)
            assert abs(msg.log_time - time.time_ns()) < 60e9, 'log time: receive wall time'
            got[msg.topic].append(msg)
        decoded = [deserialize_message(m.data, PlantOutput) for m in got['/y']]
        steps = [m.step for m in decoded]
        assert steps == list(range(steps[0], steps[0] + len(steps))), 'every sample, in order'
        probe.wait_for(lambda: steps[-1] in ys, TIMEOUT, 'the probe to get the same samples')
        assert all(m == ys[m.step] for m in decoded)
        assert len({m.y[0] for m in decoded}) > 40, 'the samples differ'
        probe.wait_for(lambda: infos, TIMEOUT, "the probe's plant_info")
        assert deserialize_message(got['/plant_info'][0].data, PlantInfo) == infos[-1]
        assert infos[-1].rate_hz == 50.0

        # plant_info went out once, long ago: the node sends it again to a new subscriber,
        # here one that offers only the ws-protocol's subprotocol.
        with FoxgloveClient(url, TIMEOUT, subprotocols=[WS_PROTOCOL]) as late:
            assert late.subprotocol == WS_PROTOCOL
            late.subscribe(late.channel('/plant_info', TIMEOUT))
            msg = late.message(TIMEOUT)
            assert msg.topic == '/plant_info'
            assert deserialize_message(msg.data, PlantInfo) == infos[-1]
        assert len(infos) == 1, 'the plant published plant_info once'
        stop_cleanly(procs, plant)
        stop_cleanly(procs, live)       # with a client connected, which it disconnects
        with pytest.raises(ConnectionClosed):
            while True:                 # the frames sent before, then the end
                client.message(TIMEOUT)


def raw_handshake(port: int, subprotocol: str) -> tuple:
    """An RFC 6455 upgrade request over a plain socket, offering `subprotocol` ('' none).

    Returns (status code, headers with lower-case names, the bytes after the head, the socket,
    the Sec-WebSocket-Accept value the RFC requires for the key sent)."""
    key = base64.b64encode(os.urandom(16)).decode()
    offer = f'Sec-WebSocket-Protocol: {subprotocol}\r\n' if subprotocol else ''
    sock = socket.create_connection(('127.0.0.1', port), timeout=TIMEOUT)
    sock.sendall((f'GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n'
                  f'Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n'
                  f'Sec-WebSocket-Version: 13\r\n{offer}\r\n').encode())
    data = b''
    while b'\r\n\r\n' not in data:
        chunk = sock.recv(65536)
        assert chunk, f'the server hung up after {data!r}'
        data += chunk
    head, _, rest = data.partition(b'\r\n\r\n')
    status, *lines = head.decode().split('\r\n')
    headers = {name.strip().lower(): value.strip()
               for name, _, value in (line.partition(':') for line in lines)}
    accept = base64.b64encode(hashlib.sha1(
        (key + '258EAFA5-E914-47DA-95CA-C5AB0DC85B11').encode()).digest()).decode()
    return int(status.split()[1]), headers, rest, sock, accept


def read_text_frame(sock: socket.socket, data: bytes) -> str:
    """The first frame of a server's stream (unmasked, RFC 6455 5.2), which must be text;
    `data`: what was already read."""
    def need(n: int) -> None:
        nonlocal data
        while len(data) < n:
            chunk = sock.recv(65536)
            assert chunk, 'the server hung up'
            data += chunk
    need(2)
    assert data[0] == 0x81, f'a final text frame, got {data[:2]!r}'
    length, start = data[1] & 0x7F, 2
    if length == 126:
        need(4)
        length, start = struct.unpack_from('>H', data, 2)[0], 4
    elif length == 127:
        need(10)
        length, start = struct.unpack_from('>Q', data, 2)[0], 10
    need(start + length)
    return data[start:start + length].decode()


@pytest.fixture
def live_server():
    """A LiveServer (no ROS) on a free port with one channel, /a, of a stand-in type."""
    server = LiveServer('test', '127.0.0.1', 0,
                        definitions=lambda name: MessageDefinition('ros2msg', 'float64 x'))
    server.add_topic('/a', 'pkg/msg/A', latched=False)
    yield server
    server.close()


def test_a_ws_protocol_client_gets_a_session_under_its_own_subprotocol(live_server):
    """@foxglove/ws-protocol offers only foxglove.websocket.v1: the handshake succeeds under
    that name (a valid accept key), the session starts with serverInfo, and a subscriber
    gets the channel's messages (the SDK alone answers HTTP 400)."""
    status, headers, rest, sock, accept = raw_handshake(live_server.port, WS_PROTOCOL)
    with sock:
        assert status == 101, (headers, rest)
        assert headers['sec-websocket-protocol'] == WS_PROTOCOL
        assert headers['sec-websocket-accept'] == accept
        assert json.loads(read_text_frame(sock, rest))['op'] == 'serverInfo'
    with FoxgloveClient(f'ws://127.0.0.1:{live_server.port}', TIMEOUT,
                        subprotocols=[WS_PROTOCOL]) as client:
        assert client.subprotocol == WS_PROTOCOL
        client.subscribe(client.channel('/a', TIMEOUT))
        payload = struct.pack('<4xd', 2.5)     # CDR little endian: header, then x
        deadline = time.monotonic() + TIMEOUT
        while True:     # the subscription takes effect some time after it is sent
            live_server.publish('/a', payload, 123)
            try:
                msg = client.message(0.2)
                break
            except TimeoutError:
                assert time.monotonic() < deadline, 'no message within the timeout'
        assert (msg.topic, msg.log_time, msg.data) == ('/a', 123, payload)


@pytest.mark.parametrize('offer', ['', 'foxglove.websocket.v2'])
def test_a_client_offering_neither_subprotocol_is_told_which_to_offer(live_server, offer):
    status, headers, rest, sock, _ = raw_handshake(live_server.port, offer)
    with sock:
        while len(rest) < int(headers['content-length']):
            rest += sock.recv(65536)
    assert status == 400
    assert 'offer the WebSocket subprotocol foxglove.sdk.v1' in rest.decode(), rest


def test_the_sdk_subprotocol_goes_through_unchanged(live_server):
    status, headers, rest, sock, accept = raw_handshake(live_server.port, 'foxglove.sdk.v1')
    with sock:
        assert (status, headers['sec-websocket-protocol']) == (101, 'foxglove.sdk.v1')
        assert headers['sec-websocket-accept'] == accept
        assert json.loads(read_text_frame(sock, rest))['op'] == 'serverInfo'


def test_bad_port_is_one_line_and_exit_2(procs):
    started = {port: procs.start('metampc_recording', 'foxglove', params={'port': port})
               for port in (-1, 70000)}
    for port, proc in started.items():
        code = proc.wait(TIMEOUT)
        lines = own_lines(procs.output(proc))
        assert code == 2, lines
        assert len(lines) == 1, lines
        assert f'invalid parameter: port must be in [0, 65535], got {port}' in lines[0]


def test_port_in_use_is_one_clear_line_and_exit_2(procs):
    with socket.socket() as holder:
        holder.bind(('127.0.0.1', 0))
        holder.listen()
        port = holder.getsockname()[1]
        proc = procs.start('metampc_recording', 'foxglove', params={'port': port})
        code = proc.wait(TIMEOUT)
    lines = own_lines(procs.output(proc))
    assert code == 2, lines
    assert len(lines) == 1, lines
    assert (f'invalid parameter: port: cannot serve on 127.0.0.1:{port}: '
            'Address already in use') in lines[0]


LAYOUT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'src',
                      'metampc_recording', 'foxglove', 'metampc_layout.json')


def _panels(tree) -> list:
    """Panel ids of a layout tree (mosaic: an id, or {first, second, direction})."""
    if isinstance(tree, str):
        return [tree]
    return _panels(tree['first']) + _panels(tree['second'])


def test_layout_plots_fields_the_graph_publishes():
    """Every plotted path is a field of its topic's type (the graph's default names,
    docs/architecture.md) or of a script's output; the scripts read fields that exist."""
    with open(LAYOUT) as f:
        layout = json.load(f)
    assert sorted(_panels(layout['layout'])) == sorted(layout['configById'])
    fields = {f'/{topic}': set(message_class(type_name).get_fields_and_field_types())
              for type_name, topic in DEFAULT_TOPICS.items()}
    for script in layout['userNodes'].values():
        source = script['sourceCode']
        output = re.search(r'export const output = "([^"]+)"', source).group(1)
        inputs = json.loads(re.search(r'export const inputs = (\[[^\]]*\])', source).group(1))
        assert output.startswith('/foxglove_script/') and inputs
        readable = set().union(*(fields[topic] for topic in inputs))
        read = set(re.findall(r'message\.(\w+)', source))
        assert read and read <= readable, (script['name'], read - readable)
        output_type = re.search(r'type Output = \{([^}]*)\}', source).group(1)
        fields[output] = set(re.findall(r'(\w+):', output_type))
    plotted = [p['value'] for config in layout['configById'].values() for p in config['paths']]
    assert len(plotted) >= 10
    for path in plotted:
        topic, field = re.fullmatch(r'(/[\w/]+)\.(\w+)(\[\d*:?\])?', path).group(1, 2)
        assert field in fields[topic], path
    titles = ' '.join(config['foxglovePanelTitle'] for config in layout['configById'].values())
    for panel in ('x1 and reference', 'u and its bounds', 'solve time', 'model version',
                  'MPC plan'):
        assert panel in titles
