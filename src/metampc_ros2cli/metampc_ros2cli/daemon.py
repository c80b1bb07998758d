"""ros2cli's daemon: one process per ROS domain that keeps the graph, so that the list verbs
answer at once, complete.

A verb's own node discovers the graph afresh and under LOCALHOST discovery often misses nodes,
so `ros2 node list`, `ros2 topic list|find|info` and `ros2 service list|find` ask a daemon
whose node has been in the graph since it started (``--no-daemon`` bypasses it). One daemon per
(user, ROS_DOMAIN_ID, discovery range, static peers) on a UNIX socket: a request is one JSON
line ``{"call": NAME, "args": [...]}`` (a query of :data:`GRAPH_CALLS` or
:data:`TOPIC_CALLS`, ``ping`` or ``stop``), the answer one JSON line ``{"result": ...}``; a
daemon younger than :data:`WARMUP_S` waits until it is that old before it answers. It ends on
``stop``, SIGINT/SIGTERM or after :data:`IDLE_S` without a request, and outlives the verb that
started it (no lifeline). See docs/nodes.md.
"""
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
from typing import Any, Iterator

GRAPH_CALLS = ('get_node_names_and_namespaces', 'get_topic_names_and_types',
               'get_service_names_and_types')
# Queries about one topic (its name the one argument), as ros2cli's daemon answers them; the
# endpoints come back as their text (rclpy's TopicEndpointInfo printed), what `topic info -v`
# prints.
TOPIC_CALLS = ('count_publishers', 'count_subscribers', 'get_publishers_info_by_topic',
               'get_subscriptions_info_by_topic')
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


class GraphProxy:
    """Stands for a node in the verbs that read the graph: its graph queries are the daemon's
    answers, and it has the name and namespace a verb's own node has (to expand a relative
    name)."""

    def __getattr__(self, name: str) -> Any:
        if name in GRAPH_CALLS:
            return lambda: [tuple(pair) for pair in request(name)]
        if name in TOPIC_CALLS:
            return lambda topic: request(name, topic)
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
                else:
                    reply = {'error': f'unknown call {call!r}'}
            except (ValueError, KeyError, TypeError, RuntimeError) as err:
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
