"""A front for the SDK's WebSocket server that also admits clients of ``foxglove.websocket.v1``.

No rclpy. The Foxglove SDK's server (foxglove-sdk 0.30.3) accepts only the subprotocol
``foxglove.sdk.v1``, the Foxglove WebSocket protocol v1 under a new name.
:class:`SubprotocolFront` listens on the public address and relays each connection to the
SDK's server on a loopback port: an upgrade request that offers ``foxglove.sdk.v1`` goes through
untouched; one that offers only ``foxglove.websocket.v1`` is passed on as ``foxglove.sdk.v1``
and the answer passed back as ``foxglove.websocket.v1`` (the Sec-WebSocket-Accept key stays
valid); anything else is refused with HTTP 400 and a body naming both. After the handshake
the bytes are relayed unchanged. Why: docs/foxglove.md.
"""
import socket
import threading
import time
from typing import List, Optional, Set, Tuple

SDK_SUBPROTOCOL = 'foxglove.sdk.v1'
WS_PROTOCOL_SUBPROTOCOL = 'foxglove.websocket.v1'
REFUSAL = (f'offer the WebSocket subprotocol {SDK_SUBPROTOCOL} (or {WS_PROTOCOL_SUBPROTOCOL}, '
           'the same protocol v1 under its older name)')
_PROTOCOL_HEADER = b'sec-websocket-protocol'
_HEAD_END = b'\r\n\r\n'
_MAX_HEAD = 65536           # bytes: an upgrade request longer than this is refused
_HANDSHAKE_TIMEOUT = 30.0   # s a client may take to send its upgrade request
_CHUNK = 65536


class HandshakeError(Exception):
    """A request the front refuses (the reason goes to the client)."""


def _read_head(sock: socket.socket) -> Tuple[bytes, bytes]:
    """An HTTP head (through the blank line) and whatever followed it in the same reads."""
    data = b''
    while _HEAD_END not in data:
        chunk = sock.recv(_CHUNK)
        if not chunk:
            raise HandshakeError('the connection ended inside the HTTP head')
        data += chunk
        if len(data) > _MAX_HEAD and _HEAD_END not in data:
            raise HandshakeError(f'HTTP head longer than {_MAX_HEAD} bytes')
    end = data.index(_HEAD_END) + len(_HEAD_END)
    return data[:end], data[end:]


def _offered(lines: List[bytes]) -> List[str]:
    """The subprotocols that Sec-WebSocket-Protocol header lines offer, in order."""
    offers = []
    for line in lines:
        name, _, value = line.partition(b':')
        if name.strip().lower() == _PROTOCOL_HEADER:
            offers += [v.strip() for v in value.decode('latin-1').split(',') if v.strip()]
    return offers


def _with_protocol(lines: List[bytes], protocol: str) -> bytes:
    """The head with every Sec-WebSocket-Protocol line replaced by one naming `protocol`."""
    kept = [line for line in lines
            if line.partition(b':')[0].strip().lower() != _PROTOCOL_HEADER]
    kept.insert(1, b'Sec-WebSocket-Protocol: ' + protocol.encode())
    return b'\r\n'.join(kept) + _HEAD_END


def upstream_request(head: bytes) -> Tuple[bytes, Optional[str]]:
    """The request to pass to the SDK and the subprotocol to answer the client with instead of
    the SDK's (None: the SDK's answer goes back unchanged).

    Raises:
        HandshakeError: the request offers neither subprotocol.
    """
    lines = head[:-len(_HEAD_END)].split(b'\r\n')
    offers = _offered(lines)
    if SDK_SUBPROTOCOL in offers:
        return head, None
    if WS_PROTOCOL_SUBPROTOCOL in offers:
        return _with_protocol(lines, SDK_SUBPROTOCOL), WS_PROTOCOL_SUBPROTOCOL
    raise HandshakeError(f'{REFUSAL}; offered: {", ".join(offers) or "none"}')


def client_response(head: bytes, answer_as: Optional[str]) -> bytes:
    """The SDK's response head as the client gets it (subprotocol `answer_as` if given)."""
    if answer_as is None:
        return head
    lines = head[:-len(_HEAD_END)].split(b'\r\n')
    if not _offered(lines):         # a refusal: nothing to rename
        return head
    return _with_protocol(lines, answer_as)


def refusal(reason: str) -> bytes:
    """HTTP 400 whose body is `reason`."""
    body = reason.encode() + b'\n'
    return (b'HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain; charset=utf-8\r\n'
            b'Content-Length: ' + str(len(body)).encode() + b'\r\nConnection: close\r\n\r\n'
            + body)


def _end(sock: socket.socket) -> None:
    """Shut both directions of `sock`; one the peer or the other relay already ended raises
    OSError (ENOTCONN), which is the state wanted."""
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        return


def _pump(source: socket.socket, sink: socket.socket) -> None:
    """Copy `source` to `sink` until either ends (EOF, or a reset: OSError); then end both
    directions of both."""
    try:
        while data := source.recv(_CHUNK):
            sink.sendall(data)
    except OSError:     # a peer reset or closed: the relay's end, like EOF
        pass
    for sock in (source, sink):
        _end(sock)


class SubprotocolFront:
    """Listens on host:port and relays each WebSocket connection to 127.0.0.1:`upstream_port`.

    Args:
        host: address to listen on (a name or an IPv4/IPv6 address).
        port: TCP port (0: a free one, see :attr:`port`).
        upstream_port: the SDK server's port on 127.0.0.1.

    Raises:
        OSError: cannot listen there (port in use, unknown host).
    """

    def __init__(self, host: str, port: int, upstream_port: int):
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
        self._listener = socket.socket(family, kind, proto)
        try:    # socket.create_server's steps, but its errors keep the OS's plain wording
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(address)
            self._listener.listen()
        except OSError:
            self._listener.close()
            raise
        self._upstream = ('127.0.0.1', upstream_port)
        self._lock = threading.Lock()
        self._open: Set[socket.socket] = set()
        self._threads: List[threading.Thread] = []
        self._closed = False
        self._start(self._accept)

    @property
    def port(self) -> int:
        """The port the front listens on."""
        return self._listener.getsockname()[1]

    def _start(self, target, *args) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)
        with self._lock:
            self._threads = [t for t in self._threads if t.is_alive()] + [thread]
        thread.start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:         # close() shut the listener down
                return
            with self._lock:
                if self._closed:
                    client.close()
                    return
                self._open.add(client)
            self._start(self._serve, client)

    def _serve(self, client: socket.socket) -> None:
        """One connection: the handshake (refused, or passed on), then the relay."""
        upstream = None
        try:
            client.settimeout(_HANDSHAKE_TIMEOUT)
            head, rest = _read_head(client)
            try:
                request, answer_as = upstream_request(head)
            except HandshakeError as err:
                client.sendall(refusal(str(err)))
                return
            upstream = socket.create_connection(self._upstream)
            with self._lock:
                self._open.add(upstream)
            upstream.sendall(request + rest)
            response, rest = _read_head(upstream)
            client.sendall(client_response(response, answer_as) + rest)
            client.settimeout(None)
            relay = threading.Thread(target=_pump, args=(client, upstream), daemon=True)
            relay.start()
            _pump(upstream, client)
            relay.join()
        except (OSError, HandshakeError):
            pass                    # the client or the server went away mid-handshake
        finally:
            with self._lock:
                self._open.discard(client)
                self._open.discard(upstream)
            client.close()
            if upstream is not None:
                upstream.close()

    def close(self, timeout: float = 5.0) -> None:
        """Stop listening; wait up to `timeout` s for the relays to end (the SDK's server
        stopped first ends them after its close frames), then cut the rest."""
        with self._lock:
            self._closed = True
            threads = list(self._threads)
        _end(self._listener)    # wakes accept() on Linux
        self._listener.close()
        deadline = time.monotonic() + timeout
        for thread in threads:
            thread.join(max(deadline - time.monotonic(), 0.0))
        with self._lock:
            for sock in self._open:
                _end(sock)
