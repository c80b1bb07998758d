"""A minimal client of the Foxglove WebSocket protocol (v1), for tests and benchmarks.

What Foxglove does when it connects to a live view: read ``serverInfo`` and the ``advertise``d
channels (JSON text frames), ``subscribe`` to some, then take MessageData binary frames:
opcode 1 (u8), subscription id (u32 LE), log time in ns (u64 LE), the payload (here CDR).
It offers the subprotocols ``foxglove.sdk.v1`` (the SDK's) and ``foxglove.websocket.v1`` (the
ws-protocol's; the live view admits either, :mod:`.subprotocol_front`), or those given. No
rclpy.
"""
import json
import re
import struct
import time
from typing import Dict, List, NamedTuple, Sequence

from websockets.sync.client import connect

SUBPROTOCOLS = ('foxglove.sdk.v1', 'foxglove.websocket.v1')
MESSAGE_DATA = 1
STATUS_ERROR = 2
_UNKNOWN_CHANNEL = re.compile(r'Unknown channel ID: (\d+)')
_HEADER = struct.Struct('<BIQ')     # opcode, subscription id, log time


class Message(NamedTuple):
    """One MessageData frame: its channel's topic, log time (ns), payload and receipt time
    (``time.time_ns()`` when the frame was read)."""

    topic: str
    log_time: int
    data: bytes
    received_ns: int


class FoxgloveClient:
    """Connected to `url` offering `subprotocols`; `server_info` is the server's first message.

    Attributes:
        server_info: the ``serverInfo`` object.
        subprotocol: the one the server chose.
        channels: advertised channels by id (the ``advertise`` objects), kept up to date.
    """

    def __init__(self, url: str, timeout: float = 10.0,
                 subprotocols: Sequence[str] = SUBPROTOCOLS):
        # No keepalive pings: a test reads only when it asks for a message, and meanwhile the
        # unread frames hold the pongs back.
        self._ws = connect(url, subprotocols=list(subprotocols), open_timeout=timeout,
                           max_size=None, ping_interval=None, legacy=True)
        self.subprotocol = self._ws.subprotocol
        self.server_info = json.loads(self._ws.recv(timeout))
        if self.server_info.get('op') != 'serverInfo':
            raise ValueError(f'expected serverInfo first, got {self.server_info!r}')
        self.channels: Dict[int, dict] = {}
        self._topics: Dict[int, str] = {}       # subscription id -> topic
        self._subscribed: Dict[int, int] = {}   # channel id -> subscription id
        self.resubscribed = 0
        self._pending: List[Message] = []

    def __enter__(self) -> 'FoxgloveClient':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _read(self, timeout: float) -> None:
        """Take one frame: a channel update is applied, a message kept for `message`."""
        frame = self._ws.recv(timeout)
        received = time.time_ns()
        if isinstance(frame, str):
            op = json.loads(frame)
            if op['op'] == 'advertise':
                self.channels.update((ch['id'], ch) for ch in op['channels'])
            elif op['op'] == 'unadvertise':
                for channel_id in op['channelIds']:
                    self.channels.pop(channel_id, None)
            elif op['op'] == 'status' and op['level'] == STATUS_ERROR:
                self._retry(op['message'])
            return
        opcode, subscription, log_time = _HEADER.unpack_from(frame)
        if opcode == MESSAGE_DATA:
            self._pending.append(Message(self._topics[subscription], log_time,
                                         bytes(frame[_HEADER.size:]), received))

    def channel(self, topic: str, timeout: float) -> dict:
        """The advertised channel of `topic`, waiting up to `timeout` s for it."""
        deadline = time.monotonic() + timeout
        while True:
            for channel in self.channels.values():
                if channel['topic'] == topic:
                    return channel
            self._read(max(deadline - time.monotonic(), 0.0))   # TimeoutError at the end

    def subscribe(self, channel: dict) -> None:
        """Subscribe to an advertised channel (one subscription per channel)."""
        subscription = len(self._topics) + 1
        self._topics[subscription] = channel['topic']
        self._subscribed[channel['id']] = subscription
        self._send_subscribe(channel['id'])

    def _send_subscribe(self, channel_id: int) -> None:
        self._ws.send(json.dumps({'op': 'subscribe', 'subscriptions': [
            {'id': self._subscribed[channel_id], 'channelId': channel_id}]}))

    def _retry(self, error: str) -> None:
        """Subscribe again to a channel the server called unknown although it had advertised it.

        The SDK (0.30.3, ``ConnectedClient::advertise_channels``) sends the advertisement
        before it enters the channel in the client's map, so a subscription that comes back
        within that window is refused (seen here in 1 of 12 runs on a loaded 2-core machine).
        The refusal is only an error status naming the channel id.
        """
        match = _UNKNOWN_CHANNEL.fullmatch(error)
        if match and int(match.group(1)) in self._subscribed:
            self.resubscribed += 1
            self._send_subscribe(int(match.group(1)))

    def message(self, timeout: float) -> Message:
        """The next message of a subscribed channel; TimeoutError after `timeout` s."""
        deadline = time.monotonic() + timeout
        while not self._pending:
            self._read(max(deadline - time.monotonic(), 0.0))
        return self._pending.pop(0)

    def close(self) -> None:
        self._ws.close()
