"""The live view's server: ROS 2 topics as Foxglove channels whose messages are the CDR bytes.

No rclpy. :class:`LiveServer` runs the Foxglove SDK's WebSocket server (subprotocol
``foxglove.sdk.v1``) on a free loopback port behind a
:class:`.subprotocol_front.SubprotocolFront` on host:port. Each topic becomes a channel of
message encoding ``cdr`` whose schema is the type's complete definition (:mod:`.msg_schema`,
``ros2msg`` or ``ros2idl``), so Foxglove decodes the bytes as received from DDS. The server
keeps no history: a latched topic's newest message is sent again whenever a client subscribes
to it (every client of that channel gets it). See docs/foxglove.md.
"""
import time
from typing import Callable, Dict, Optional

import foxglove
from foxglove import Channel, Schema
from foxglove.websocket import ChannelView, Client, ServerListener
from metampc_recording.msg_schema import DefinitionSource, MessageDefinition
from metampc_recording.subprotocol_front import SubprotocolFront

MESSAGE_ENCODING = 'cdr'


class LiveServer(ServerListener):
    """A Foxglove WebSocket server whose channels carry raw CDR messages.

    Args:
        name: the server's name (in its serverInfo).
        host: address to listen on.
        port: TCP port (0: a free one, see :attr:`port`).
        definitions: type name ('pkg/msg/Type') -> complete definition (default: the ament
            index's, :class:`.msg_schema.DefinitionSource`).
        clock: now in ns, the log time of a latched message sent again (default: wall time).

    Raises:
        OSError: the server cannot listen there (port in use, unknown host).
    """

    def __init__(self, name: str, host: str, port: int,
                 definitions: Optional[Callable[[str], MessageDefinition]] = None,
                 clock: Callable[[], int] = time.time_ns):
        self._definitions = definitions or DefinitionSource().get
        self._clock = clock
        self._context = foxglove.Context()
        self._channels: Dict[str, Channel] = {}
        self._by_id: Dict[int, Channel] = {}
        self._latched: Dict[int, Optional[bytes]] = {}   # channel id -> newest message
        self._server = foxglove.start_server(name=name, host='127.0.0.1', port=0,
                                             context=self._context, server_listener=self)
        try:
            self._front = SubprotocolFront(host, port, self._server.port)
        except OSError as err:
            self._server.stop()
            raise OSError(f'cannot serve on {host}:{port}: {err.strerror or err}') from None

    @property
    def port(self) -> int:
        """The port the server listens on (its front's)."""
        return self._front.port

    def add_topic(self, topic: str, type_name: str, latched: bool) -> None:
        """Advertise `topic` to every client (and to those that connect later).

        Raises:
            msg_schema.DefinitionNotFoundError: no definition of the type is installed.
            ValueError: a malformed type name.
        """
        definition = self._definitions(type_name)
        schema = Schema(name=type_name, encoding=definition.encoding,
                        data=definition.text.encode())
        channel = Channel(topic, schema=schema, message_encoding=MESSAGE_ENCODING,
                          context=self._context)
        self._channels[topic] = channel
        self._by_id[channel.id()] = channel
        if latched:
            self._latched[channel.id()] = None

    def publish(self, topic: str, data: bytes, log_time: int) -> None:
        """Send one message of `topic` (CDR bytes) to the clients subscribed to it; log_time
        in ns."""
        channel = self._channels[topic]
        if channel.id() in self._latched:
            self._latched[channel.id()] = data
        channel.log(data, log_time=log_time)

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        """The SDK's callback (its own thread): send a latched topic's newest message again."""
        data = self._latched.get(channel.id)
        if data is not None:
            self._by_id[channel.id].log(data, log_time=self._clock())

    def close(self) -> None:
        """Stop the server (clients are disconnected) and close every channel."""
        self._server.stop()
        self._front.close()
        for channel in self._channels.values():
            channel.close()
