"""ros2cli's daemon: one process per ROS domain that keeps the graph, so that the list verbs
answer at once, complete (a verb's own node discovers the graph afresh and often misses nodes).

`ros2 node list|info`, `topic list|find|info` and `service list|find` ask the daemon, and
`ros2 param` has its node call the parameter services (:func:`call_service`; ``--no-daemon``
bypasses it). One daemon per (user, ROS_DOMAIN_ID, discovery range, static peers) on a UNIX
socket: a request is one JSON line ``{"call": NAME, "args": [...]}`` (:data:`GRAPH_CALLS`,
:data:`TOPIC_CALLS`, :data:`NODE_CALLS`, :data:`SERVICE_CALL`, ``ping``, ``stop``), the answer
``{"result": ...}``; it answers once :data:`WARMUP_S` old, ends on ``stop``, SIGINT/SIGTERM or
after :data:`IDLE_S` idle, and outlives the verb that started it. See docs/nodes.md.
"""
import base64
import contextlib
import fcntl
import hashlib
import json
import os
import signal
import socket
import socketserver
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, Iterator, Optional

GRAPH_CALLS = ('get_node_names_and_namespaces', 'get_topic_names_and_types',
               'get_service_names_and_types')
# Queries about one topic (its name the one argument), as ros2cli's daemon answers them; the
# endpoints come back as their text (rclpy's TopicEndpointInfo printed), what `topic info -v`
# prints.
TOPIC_CALLS = ('count_publishers', 'count_subscribers', 'get_publishers_info_by_topic',
               'get_subscriptions_info_by_topic')
# Queries about one node (its name and namespace the arguments), as `ros2 node info` asks
# them; the action ones are rclpy.action's functions of the daemon's node.
NODE_CALLS = ('get_subscriber_names_and_types_by_node', 'get_publisher_names_and_types_by_node',
              'get_service_names_and_types_by_node', 'get_client_names_and_types_by_node',
              'get_action_server_names_and_types_by_node',
              'get_action_client_names_and_types_by_node')
# A service call by the daemon's node: (service name, 'pkg/srv/Type', the request serialized
# (CDR, base64), timeout s) -> the response serialized, or None: no answer within the timeout.
SERVICE_CALL = 'call_service'
SERVICE_POLL_S = 0.01   # s between two looks at whether a new client has matched its service
WARMUP_S = 3.5          # s: the others' next announcement reaches a new participant (here: ~3)
IDLE_S = 2 * 3600.0     # s without a request before a daemon ends (ros2cli's timeout)
START_S = 15.0          # s for a daemon to answer after it was started (imports rclpy)
ANSWER_S = 10.0         # s for one answer (a warm-up included)
NODE_NAME = '_ros2cli_daemon'   # hidden, as ros2cli's


class DaemonError(RuntimeError):
    """No daemon answers (and none could be started)."""


def address() -> str:
    """The socket of this environment's daemon: one per user, domain, range and peers."""
    env = os.environ
    key = '|'.join((env.get('ROS_DOMAIN_ID', '0'), env.get('ROS_AUTOMATIC_DISCOVERY_RANGE', ''),
                    env.get('ROS_STATIC_PEERS', ''), env.get('ROS_LOCALHOST_ONLY', '')))
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    return os.path.join(tempfile.gettempdir(), f'metampc-ros2-daemon-{os.getuid()}-{digest}')


def request(call: str, *args: Any, timeout: float = ANSWER_S) -> Any:
    """Ask the running daemon; DaemonError if none answers."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
            conn.settimeout(timeout)
            conn.connect(address())
            conn.sendall(json.dumps({'call': call, 'args': list(args)}).encode() + b'\n')
            with conn.makefile('rb') as answer:
                line = answer.readline()
    except OSError as err:
        raise DaemonError(f'no daemon answers on {address()} ({err.strerror or err})') from None
    if not line:
        raise DaemonError('the daemon closed the connection without an answer')
    reply = json.loads(line)
    if 'error' in reply:
        raise DaemonError(reply['error'])
    return reply['result']


def running() -> bool:
    try:
        request('ping', timeout=2.0)
    except DaemonError:
        return False
    return True


def start() -> bool:
    """Start this environment's daemon unless one runs; True if one was started. Waits until
    it answers with the whole graph (its warm-up); DaemonError if it does not within
    START_S."""
    if running():
        return False
    env = {k: v for k, v in os.environ.items() if k != 'METAMPC_LIFELINE'}
    subprocess.Popen([sys.executable, '-m', 'metampc_ros2cli.daemon'], env=env,
                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + START_S
    while not running():
        if time.monotonic() > deadline:
            raise DaemonError(f'a daemon was started but does not answer on {address()}')
        time.sleep(0.05)
    request(GRAPH_CALLS[0])     # returns once the warm-up is over
    return True


def stop() -> bool:
    """Stop this environment's daemon; True if one was running."""
    if not running():
        return False
    with contextlib.suppress(DaemonError):
        request('stop')
    return True


def call_service(service: str, srv: Any, request_msg: Any, timeout: float) -> Optional[Any]:
    """The response of `service` (of service class `srv`) to `request_msg`, called by the
    daemon's node, which knows the graph already (DaemonError if no daemon answers); None if
    the service does not answer within `timeout` s."""
    from rclpy.serialization import deserialize_message, serialize_message
    type_name = f'{srv.__module__.split(".")[0]}/srv/{srv.__name__}'
    answer = request(SERVICE_CALL, service, type_name,
                     base64.b64encode(serialize_message(request_msg)).decode(), timeout,
                     timeout=timeout + ANSWER_S)
    return None if answer is None else deserialize_message(base64.b64decode(answer),
                                                           srv.Response)


def _serve_call(node: Any, clients: dict, lock: threading.Lock, service: str, type_name: str,
                payload: str, timeout: float) -> Optional[str]:
    """:data:`SERVICE_CALL` in the daemon: one client per (service, type), kept."""
    from rclpy.serialization import deserialize_message, serialize_message

    from metampc_common.message_types import message_class
    srv = message_class(type_name)
    with lock:
        client = clients.get((service, type_name))
        if client is None:
            client = clients[service, type_name] = node.create_client(srv, service)
    deadline = time.monotonic() + timeout
    while not client.service_is_ready():
        if time.monotonic() > deadline:
            return None
        time.sleep(SERVICE_POLL_S)
    done = threading.Event()
    future = client.call_async(deserialize_message(base64.b64decode(payload), srv.Request))
    future.add_done_callback(lambda _: done.set())
    if not done.wait(max(0.0, deadline - time.monotonic())):
        client.remove_pending_request(future)
        return None
    return base64.b64encode(serialize_message(future.result())).decode()


class GraphProxy:
    """Stands for a node in the verbs that read the graph: its graph queries are the daemon's
    answers, and it has the name and namespace a verb's own node has (to expand a relative
    name)."""

    def __getattr__(self, name: str) -> Any:
        if name in GRAPH_CALLS:
            return lambda: [tuple(pair) for pair in request(name)]
        if name in TOPIC_CALLS:
            return lambda topic: request(name, topic)
        if name in NODE_CALLS:
            return lambda *node: [tuple(pair) for pair in request(name, *node)]
        raise AttributeError(name)

    @staticmethod
    def get_name() -> str:
        from metampc_ros2cli.direct import NODE_NAME_PREFIX
        return f'{NODE_NAME_PREFIX}_{os.getpid()}'

    @staticmethod
    def get_namespace() -> str:
        return '/'


@contextlib.contextmanager
def graph(args: Any) -> Iterator[Any]:
    """What a list verb queries: the daemon (started if need be), or with ``--no-daemon`` or
    when no daemon can start, a DirectNode of the verb's own."""
    from metampc_ros2cli.direct import DirectNode
    if not getattr(args, 'no_daemon', False):
        try:
            start()
            yield GraphProxy()
            return
        except DaemonError as err:
            print(f'ros2: {err}; asking the graph directly', file=sys.stderr)
    with DirectNode(args) as node:
        yield node


def by_node(node: Any, call: str) -> Any:
    """The query `call` of :data:`NODE_CALLS` of an rclpy node: (name, namespace) -> (name,
    types) pairs."""
    if call.startswith('get_action_'):
        import rclpy.action
        return lambda name, namespace: getattr(rclpy.action, call)(node, name, namespace)
    return getattr(node, call)


def add_arguments(parser: Any) -> None:
    """``--no-daemon`` (ros2cli's)."""
    parser.add_argument('--no-daemon', action='store_true',
                        help='Do not spawn nor use an already running daemon')


# --- the daemon process ------------------------------------------------------------------


class _Server(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    daemon_threads = True


def serve() -> int:
    """Run a daemon in this process until stop, a signal or IDLE_S without a request."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    path = address()
    # One daemon per address: the one that holds the lock (released when it ends, however).
    lock = open(path + '.lock', 'w')
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return 0
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)     # a stale socket of a daemon that died
    signal.signal(signal.SIGTERM, signal.default_int_handler)   # ends serve_forever as Ctrl-C
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f'{NODE_NAME}_{os.getpid()}', start_parameter_services=False)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    born = time.monotonic()
    last = [time.monotonic()]
    clients: dict = {}
    clients_lock = threading.Lock()

    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            last[0] = time.monotonic()
            try:
                asked = json.loads(self.rfile.readline())
                call, args = asked['call'], asked.get('args', [])
                if call == 'stop':
                    reply: Any = {'result': True}
                    threading.Thread(target=server.shutdown, daemon=True).start()
                elif call == 'ping':
                    reply = {'result': os.getpid()}
                elif call in GRAPH_CALLS:
                    time.sleep(max(0.0, born + WARMUP_S - time.monotonic()))
                    reply = {'result': [list(p) for p in getattr(node, call)()]}
                elif call in TOPIC_CALLS:
                    time.sleep(max(0.0, born + WARMUP_S - time.monotonic()))
                    result = getattr(node, call)(*args)
                    reply = {'result': result if isinstance(result, int)
                             else [str(endpoint) for endpoint in result]}
                elif call == SERVICE_CALL:
                    time.sleep(max(0.0, born + WARMUP_S - time.monotonic()))
                    reply = {'result': _serve_call(node, clients, clients_lock, *args)}
                elif call in NODE_CALLS:
                    time.sleep(max(0.0, born + WARMUP_S - time.monotonic()))
                    reply = {'result': [list(p) for p in by_node(node, call)(*args)]}
                else:
                    reply = {'error': f'unknown call {call!r}'}
            except (ValueError, KeyError, TypeError, RuntimeError, ImportError,
                    AttributeError) as err:
                reply = {'error': f'bad request: {err}'}
            self.wfile.write(json.dumps(reply).encode() + b'\n')

    server = _Server(path, Handler)

    def idle_watch() -> None:
        while time.monotonic() - last[0] < IDLE_S:
            time.sleep(min(60.0, IDLE_S))
        server.shutdown()
    threading.Thread(target=idle_watch, daemon=True).start()
    try:
        server.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        lock.close()
    return 0


if __name__ == '__main__':
    sys.exit(serve())
