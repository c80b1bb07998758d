"""Writing serialized ROS 2 messages to MCAP the way rosbag2 (Jazzy, mcap storage) does.

In: CDR bytes per topic with their type, QoS offers (:mod:`metampc_recording.rosbag2_qos`) and
receive / source times (ns); out: an MCAP file in rosbag2's layout (profile ``ros2``, one
``ros2msg`` Schema per type from :mod:`metampc_recording.msg_schema`, one ``cdr`` Channel per
topic, the ``rosbag2`` and ``metampc`` Metadata records, zstd or lz4 chunks and the summary on
:meth:`close`), and for a bag folder its ``metadata.yaml`` (:func:`write_bag_metadata_file`).
Written without a user-space buffer, so a SIGKILL leaves a file readable up to its last
complete chunk (:meth:`flush` closes one early). Refuses to overwrite an existing file. The
file layout in full: docs/recording.md. No rclpy here.
"""
import json
import os
from dataclasses import dataclass, field
from typing import Callable, Dict, Optional, Sequence

from mcap.exceptions import UnsupportedCompressionError
from mcap.writer import CompressionType, LIBRARY_IDENTIFIER, Writer
from metampc_recording.msg_schema import DefinitionSource, MessageDefinition
from metampc_recording.rosbag2_qos import profiles_to_dicts, profiles_to_yaml, QosProfile
import yaml

COMPRESSIONS = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4,
                'none': CompressionType.NONE}
BAG_METADATA_VERSION = 9          # rosbag2 Jazzy
RUN_METADATA_NAME = 'metampc'     # Metadata record holding the run configuration
BAG_METADATA_NAME = 'rosbag2'     # Metadata record holding the bag metadata (rosbag2's name)
BAG_METADATA_FILE = 'metadata.yaml'   # the bag metadata file of a rosbag2 bag folder
LIBRARY = f'metampc_recorder; {LIBRARY_IDENTIFIER}'


@dataclass
class McapWriterConfig:
    """Options of :class:`Rosbag2McapWriter`.

    Attributes:
        path: output file (created; an existing file is an error).
        chunk_size: uncompressed bytes after which a chunk is closed and written.
        compression: 'zstd', 'lz4' or 'none' (zstd needs the `zstandard` package).
        run_config: the run's configuration, stored as JSON in the ``metampc`` metadata record.
        ros_distro: written into the bag metadata.
    """

    path: str
    chunk_size: int = 1024 * 1024
    compression: str = 'lz4'
    run_config: Dict[str, object] = field(default_factory=dict)
    ros_distro: str = 'jazzy'

    def validate(self) -> None:
        """Raise ValueError naming the first bad option."""
        if self.compression not in COMPRESSIONS:
            raise ValueError(f'compression must be one of {sorted(COMPRESSIONS)}, '
                             f'not {self.compression!r}')
        if self.chunk_size < 1:
            raise ValueError(f'chunk_size must be positive, not {self.chunk_size}')


class _DirectFile:
    """A write-only file without user-space buffering: each write() goes to the kernel."""

    def __init__(self, path: str):
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self._pos = 0

    def write(self, data) -> int:
        view = memoryview(data)
        while view:
            written = os.write(self._fd, view)
            view = view[written:]
            self._pos += written
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        """Nothing is buffered here."""

    def close(self) -> None:
        os.close(self._fd)


@dataclass
class _Topic:
    name: str
    type_name: str
    channel_id: int
    offered: Sequence[QosProfile]
    type_hash: str
    count: int = 0


class Rosbag2McapWriter:
    """rosbag2-compatible MCAP writer of raw CDR messages (see the module docstring).

    Args:
        config: the options; validated here.
        definitions: complete message definition per type name (default: from the ament index).

    Raises:
        ValueError: bad option, or compression whose library is missing.
        FileExistsError: `config.path` exists.
    """

    def __init__(self, config: McapWriterConfig,
                 definitions: Optional[Callable[[str], MessageDefinition]] = None):
        config.validate()
        self.config = config
        self._definitions = definitions or DefinitionSource().get
        self._file = _DirectFile(config.path)
        try:
            self._writer = Writer(self._file, chunk_size=config.chunk_size,
                                  compression=COMPRESSIONS[config.compression])
        except UnsupportedCompressionError:
            self._file.close()
            os.unlink(config.path)
            raise ValueError(f'compression {config.compression!r} is not available: '
                             'install its Python package (zstd: zstandard) or use lz4') from None
        self._schemas: Dict[str, int] = {}
        self._topics: Dict[str, _Topic] = {}
        self._start_ns: Optional[int] = None
        self._end_ns = 0
        self._closed = False
        self._writer.start(profile='ros2', library=LIBRARY)
        self._write_bag_metadata()
        self._writer.add_metadata(RUN_METADATA_NAME,
                                  {'config': json.dumps(config.run_config, sort_keys=True)})

    @property
    def topics(self) -> Dict[str, int]:
        """Messages written so far, per topic."""
        return {name: t.count for name, t in self._topics.items()}

    def add_topic(self, name: str, type_name: str, offered: Sequence[QosProfile],
                  type_hash: str = '') -> int:
        """Register a topic (and its type's schema, once per type); returns its channel id.

        Args:
            name: fully qualified topic name, e.g. '/y'.
            type_name: 'pkg/msg/Type'.
            offered: QoS profiles of the topic's publishers when recording started.
            type_hash: the type's description hash ('RIHS01_...'), '' if unknown.

        Raises:
            ValueError: the topic is already registered with another type.
            msg_schema.DefinitionNotFoundError: no definition of the type is installed.
        """
        if name in self._topics:
            topic = self._topics[name]
            if topic.type_name != type_name:
                raise ValueError(f'topic {name} is recorded as {topic.type_name}, '
                                 f'not {type_name}')
            return topic.channel_id
        if type_name not in self._schemas:
            definition = self._definitions(type_name)
            self._schemas[type_name] = self._writer.register_schema(
                type_name, definition.encoding, definition.text.encode())
        channel_id = self._writer.register_channel(
            name, 'cdr', self._schemas[type_name],
            {'offered_qos_profiles': profiles_to_yaml(offered), 'topic_type_hash': type_hash})
        self._topics[name] = _Topic(name, type_name, channel_id, list(offered), type_hash)
        return channel_id

    def write(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int,
              sequence: int = 0) -> None:
        """Append one serialized message of a registered topic.

        Args:
            topic: topic name given to :meth:`add_topic`.
            data: the CDR bytes as received (encapsulation header included).
            log_time_ns: receive time, ns since the epoch of the recorder's clock.
            publish_time_ns: the publisher's send time, ns.
            sequence: publisher sequence number (uint32, wraps), 0 if unknown.
        """
        entry = self._topics[topic]
        self._writer.add_message(entry.channel_id, log_time_ns, data, publish_time_ns,
                                 sequence & 0xFFFFFFFF)
        entry.count += 1
        if self._start_ns is None or log_time_ns < self._start_ns:
            self._start_ns = log_time_ns
        self._end_ns = max(self._end_ns, log_time_ns)

    def flush(self) -> None:
        """Close the chunk in progress (if it holds messages) and hand it to the kernel."""
        self._writer.flush()

    def close(self) -> None:
        """Write the final bag metadata and the summary, and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._write_bag_metadata()
            self._writer.finish()
        finally:
            self._file.close()

    def _write_bag_metadata(self) -> None:
        """The ``rosbag2`` metadata record: rosbag2's BagMetadata YAML, version 9."""
        start = self._start_ns or 0
        duration = self._end_ns - start if self._start_ns is not None else 0
        count = sum(t.count for t in self._topics.values())
        file_name = os.path.basename(self.config.path)
        metadata = {
            'version': BAG_METADATA_VERSION,
            'storage_identifier': 'mcap',
            'duration': {'nanoseconds': duration},
            'starting_time': {'nanoseconds_since_epoch': start},
            'message_count': count,
            'topics_with_message_count': [{
                'topic_metadata': {
                    'name': t.name,
                    'type': t.type_name,
                    'serialization_format': 'cdr',
                    'offered_qos_profiles': profiles_to_dicts(t.offered),
                    'type_description_hash': t.type_hash,
                },
                'message_count': t.count,
            } for t in self._topics.values()],
            # Chunk compression is internal to MCAP: rosbag2 leaves these empty for it.
            'compression_format': '',
            'compression_mode': '',
            'relative_file_paths': [file_name],
            'files': [{'path': file_name,
                       'starting_time': {'nanoseconds_since_epoch': start},
                       'duration': {'nanoseconds': duration},
                       'message_count': count}],
            'custom_data': None,
            'ros_distro': self.config.ros_distro,
        }
        self._writer.add_metadata(BAG_METADATA_NAME, {'serialized_metadata': yaml.safe_dump(
            metadata, sort_keys=False, default_flow_style=False)})


def bag_folder_file(folder: str) -> str:
    """The MCAP file of rosbag2 bag folder `folder`: ``FOLDER/NAME_0.mcap``, NAME being the
    folder's own name (rosbag2's ``SequentialWriter::format_storage_uri``, first file)."""
    return os.path.join(folder, f'{os.path.basename(os.path.normpath(folder))}_0.mcap')


def write_bag_metadata_file(folder: str, serialized_metadata: str) -> str:
    """Write ``FOLDER/metadata.yaml`` from the bag metadata YAML a writer stored in its final
    ``rosbag2`` record; returns its path.

    rosbag2 writes the same metadata into the MCAP file and, under the key
    ``rosbag2_bagfile_information``, into metadata.yaml when it closes a bag; rosbag2's tools
    and ``rosbags`` open a folder through that file. An existing metadata.yaml is an error
    (FileExistsError).
    """
    path = os.path.join(folder, BAG_METADATA_FILE)
    document = {'rosbag2_bagfile_information': yaml.safe_load(serialized_metadata)}
    with open(path, 'x') as f:
        yaml.safe_dump(document, f, sort_keys=False, default_flow_style=False)
    return path
