"""Reading a ROS 2 MCAP recording, finished or cut short, with the `mcap` library.

The file is read front to back with :class:`mcap.stream_reader.StreamReader`, which needs no
summary: a finished recording yields everything (and its Statistics record), one whose writer
was killed yields every record up to the first incomplete one, i.e. every message of its
complete chunks. Messages are decoded with `mcap_ros2`'s decoder from the schemas embedded in
the file, so no ROS installation is needed. :func:`read_recording` keeps every message in
memory, or (``messages=False``) none: :meth:`Recording.raw` and :meth:`Recording.decoded` then
stream the file again, for recordings of any length. No rclpy here.
"""
import glob
import json
import os
import struct
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional, Tuple

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema, Statistics
from mcap.stream_reader import read_magic, StreamReader
from mcap.writer import MCAP0_MAGIC
from mcap_ros2.decoder import DecoderFactory
from metampc_recording.mcap_writer import RUN_METADATA_NAME


@dataclass
class RecordedTopic:
    """One channel of a recording.

    Attributes:
        name: topic name. type_name: 'pkg/msg/Type'. message_encoding: 'cdr'.
        offered_qos_profiles: rosbag2 YAML of the publishers' QoS ('' if absent).
        type_hash: 'RIHS01_...' or ''. count: messages read on this topic.
    """

    name: str
    type_name: str
    message_encoding: str
    offered_qos_profiles: str
    type_hash: str
    schema: Optional[Schema]
    count: int = 0


@dataclass
class RawMessage:
    """One recorded message: CDR `data`, times in ns, publisher sequence number."""

    topic: str
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


@dataclass
class Recording:
    """Everything read from one MCAP file.

    Attributes:
        path: the file.
        complete: True if the file ends with a footer (the writer finished it).
        topics: per topic name.
        messages: in log-time order (stable: file order among equal times); empty when read
            with ``messages=False``.
        metadata: Metadata records by name (the last one of each name).
        statistics: the summary's Statistics record (None when cut short).
        message_count: messages in the file. start_ns, end_ns: their first and last log time
            (None without messages).
    """

    path: str
    complete: bool
    topics: Dict[str, RecordedTopic]
    messages: List[RawMessage]
    metadata: Dict[str, Dict[str, str]] = field(default_factory=dict)
    statistics: Optional[Statistics] = None
    message_count: int = 0
    start_ns: Optional[int] = None
    end_ns: Optional[int] = None
    loaded: bool = True     # `messages` holds the messages (read with messages=True)

    def run_config(self) -> Dict[str, Any]:
        """The run configuration the recorder stored (``metampc`` record), {} if none."""
        text = self.metadata.get(RUN_METADATA_NAME, {}).get('config')
        return json.loads(text) if text else {}

    def raw(self, topics: Optional[Iterable[str]] = None) -> Iterator[RawMessage]:
        """The messages of `topics` (default all).

        From a recording read with its messages: in log-time order. Otherwise the file is read
        again, streamed, in file order (the order the recorder received them: log-time order
        unless its clock stepped back), holding one chunk and one message at a time.
        """
        wanted = set(self.topics if topics is None else topics)
        if not self.loaded:
            return _scan(self.path, _Summary(), wanted)
        return (m for m in self.messages if m.topic in wanted)

    def decoded(self, topics: Optional[Iterable[str]] = None
                ) -> Iterator[Tuple[RecordedTopic, RawMessage, Any]]:
        """(topic, raw message, decoded message) for `topics` (default all), in the order of
        :meth:`raw`. Decoded messages have the fields of the ROS message as attributes
        (mcap_ros2).
        """
        factory = DecoderFactory()
        decoders: Dict[str, Callable[[bytes], Any]] = {}
        for raw in self.raw(topics):
            topic = self.topics[raw.topic]
            if raw.topic not in decoders:
                decoder = factory.decoder_for(topic.message_encoding, topic.schema)
                if decoder is None:
                    raise ValueError(f'cannot decode {raw.topic}: encoding '
                                     f'{topic.message_encoding!r}, schema {topic.type_name!r}')
                decoders[raw.topic] = decoder
            yield topic, raw, decoders[raw.topic](raw.data)


class _ExactReads:
    """A binary file whose read(n) returns n bytes or raises EndOfFile.

    mcap's stream reader accepts short reads, so a record cut by the end of the file would come
    back truncated instead of failing; this makes the cut an error at the first short record.
    """

    def __init__(self, stream):
        self._stream = stream

    def read(self, size: int) -> bytes:
        data = self._stream.read(size)
        if len(data) < size:
            raise EndOfFile()
        return data


def resolve_recording(path: str) -> str:
    """The MCAP file of `path`: the file itself, or the one ``*.mcap`` in a run folder.

    Raises:
        FileNotFoundError: no such file, or a folder without an MCAP file.
        ValueError: a folder with several MCAP files, an experiment's run folder (its
            recordings are one per seed), a file that is not MCAP.
    """
    if os.path.isfile(path):
        with open(path, 'rb') as f:
            try:
                read_magic(ReadDataStream(f))
            except (McapError, struct.error):
                raise ValueError(f'{path} is not an MCAP file (it does not start with the MCAP '
                                 'magic bytes)') from None
        return path
    if not os.path.isdir(path):
        raise FileNotFoundError(f'no such file or folder: {path}')
    found = sorted(glob.glob(os.path.join(path, '*.mcap')))
    seeds = sorted(glob.glob(os.path.join(path, 'seed_*', '*.mcap')))
    if not found and seeds:
        raise ValueError(f'{path} is an experiment run folder with one recording per seed: '
                         f'replay one of them ({seeds[0]}, ...), or rebuild its reports with '
                         f'run_experiment.py --report {path}')
    if not found:
        raise FileNotFoundError(f'no .mcap file in {path}')
    if len(found) > 1:
        raise ValueError(f'several .mcap files in {path}: '
                         f'{", ".join(os.path.basename(f) for f in found)}; name one')
    return found[0]


def finished(path: str) -> bool:
    """Whether an MCAP file ends with the closing magic bytes its writer puts last (a file
    cut short, e.g. by a killed writer, does not), read without scanning the file."""
    with open(path, 'rb') as f:
        if f.seek(0, os.SEEK_END) < 2 * len(MCAP0_MAGIC):
            return False
        f.seek(-len(MCAP0_MAGIC), os.SEEK_END)
        return f.read() == MCAP0_MAGIC


@dataclass
class _Summary:
    """What a pass over a file gathers besides its messages."""

    topics: Dict[str, RecordedTopic] = field(default_factory=dict)
    metadata: Dict[str, Dict[str, str]] = field(default_factory=dict)
    statistics: Optional[Statistics] = None
    complete: bool = False
    count: int = 0
    start_ns: Optional[int] = None
    end_ns: Optional[int] = None


def _scan(path: str, got: _Summary,
          topics: Optional[Iterable[str]] = None) -> Iterator[RawMessage]:
    """The messages of `topics` (default all) of an MCAP file in file order, streamed; what
    else the file holds goes into `got` (a fresh :class:`_Summary`) as it is read.

    A file cut short ends at its first incomplete record.
    """
    wanted = None if topics is None else set(topics)
    schemas: Dict[int, Schema] = {}
    channels: Dict[int, Channel] = {}
    with open(path, 'rb') as stream:
        try:
            for record in StreamReader(_ExactReads(stream)).records:
                if isinstance(record, Message):
                    topic = channels[record.channel_id].topic
                    got.topics[topic].count += 1
                    got.count += 1
                    t = record.log_time
                    got.start_ns = t if got.start_ns is None else min(got.start_ns, t)
                    got.end_ns = t if got.end_ns is None else max(got.end_ns, t)
                    if wanted is None or topic in wanted:
                        yield RawMessage(topic, t, record.publish_time, record.sequence,
                                         record.data)
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel) and record.id not in channels:
                    channels[record.id] = record
                    got.topics[record.topic] = RecordedTopic(
                        record.topic, schemas[record.schema_id].name if record.schema_id else '',
                        record.message_encoding, record.metadata.get('offered_qos_profiles', ''),
                        record.metadata.get('topic_type_hash', ''), schemas.get(record.schema_id))
                elif isinstance(record, Metadata):
                    got.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Statistics):
                    got.statistics = record
                elif isinstance(record, Footer):
                    got.complete = True
        except McapError:
            pass    # cut short: keep every record read before the incomplete one


def read_recording(path: str, messages: bool = True) -> Recording:
    """Read an MCAP file or run folder (see :func:`resolve_recording`) into a Recording.

    Args:
        messages: keep the messages (in memory, sorted by log time); False: one streaming pass
            that keeps none (topics and counts, metadata, times), for recordings too large to
            hold: :meth:`Recording.decoded` then streams the file again.
    """
    path = resolve_recording(path)
    got = _Summary()
    kept = list(_scan(path, got, None if messages else ()))
    kept.sort(key=lambda m: m.log_time)
    return Recording(path, got.complete, got.topics, kept, got.metadata, got.statistics,
                     got.count, got.start_ns, got.end_ns, loaded=messages)
