"""What `ros2 bag info` reads of a bag and how it prints it, as rosbag2 (Jazzy) does.

A bag is a rosbag2 bag folder (``metadata.yaml`` and its files) or one MCAP file (its summary's
Statistics, channels and ``rosbag2`` metadata; without a summary, an unfinished recording, it
is scanned through and :attr:`BagInfo.scanned` says so); a folder without metadata.yaml that
holds one MCAP file is read as that file (rosbag2 refuses it). :func:`format_bag_metadata` and
:func:`format_service_info` print as rosbag2_py's functions of the same names, to the
character. Errors (a file cut short, no bag) are RuntimeError with a one-line message. No
rclpy, but for the service events of ``-v`` (:func:`count_service_requests`). The rules in
full: docs/recording.md.
"""
import os
import struct
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Set, Tuple

from mcap.exceptions import McapError
from mcap.reader import make_reader
from metampc_recording.mcap_writer import BAG_METADATA_FILE, BAG_METADATA_NAME
from metampc_recording.recording_reader import read_recording, resolve_recording
import yaml

INDENT = 19                  # rosbag2: the longest field name ('Topic information:') plus one
SERVICE_EVENT_SUFFIX = '/_service_event'     # RCL_SERVICE_INTROSPECTION_TOPIC_POSTFIX
EVENT_TYPE_SUFFIX = '_Event'                 # pkg/srv/X_Event, the type of X's events
FOOTER_OPCODE = 0x02


@dataclass
class TopicInformation:
    """One topic of a bag: rosbag2's TopicInformation (the fields info prints)."""

    name: str
    type: str
    serialization_format: str
    message_count: int


@dataclass
class BagInfo:
    """rosbag2's BagMetadata, the fields `ros2 bag info` prints, and where the data is.

    Attributes:
        relative_file_paths: the bag's files as rosbag2 names them (a single file: the path as
            given). bag_size: bytes. storage_identifier: 'mcap', ... ros_distro: '' if unknown.
        starting_time, duration: ns (since the epoch; long).
        message_count: all messages, service events included.
        topics_with_message_count: in the bag's order.
        files: paths of the bag's files on this machine.
        scanned: the counts come from reading an MCAP file without summary through.
    """

    relative_file_paths: List[str]
    bag_size: int
    storage_identifier: str
    ros_distro: str
    starting_time: int
    duration: int
    message_count: int
    topics_with_message_count: List[TopicInformation]
    files: List[str] = field(default_factory=list)
    scanned: bool = False


@dataclass
class ServiceInformation:
    """One service whose events a bag holds; the request and response counts only with -v."""

    name: str
    type: str
    serialization_format: str
    event_count: int
    request_count: int = 0
    response_count: int = 0


def is_service_event_topic(name: str, type_name: str) -> bool:
    """rosbag2_cpp::is_service_event_topic: '.../_service_event' of a 'pkg/srv/X_Event'."""
    return (len(name) > len(SERVICE_EVENT_SUFFIX) and name.endswith(SERVICE_EVENT_SUFFIX)
            and len(type_name) > len(EVENT_TYPE_SUFFIX) and '/srv/' in type_name
            and type_name.endswith(EVENT_TYPE_SUFFIX))


def read_bag_info(path: str) -> BagInfo:
    """The bag at `path`: a bag folder, a folder with one MCAP file, or an MCAP file.

    Raises:
        RuntimeError: no such path, no metadata.yaml nor MCAP file in a folder, a metadata.yaml
            that is not rosbag2's, a file that is not MCAP or is cut short (one-line message).
    """
    if not os.path.exists(path):
        raise RuntimeError(f'Bag path {path} does not exist.')
    if os.path.isdir(path):
        if os.path.isfile(os.path.join(path, BAG_METADATA_FILE)):
            return _folder_info(path)
        try:
            mcap_path = resolve_recording(path)
        except FileNotFoundError:
            raise RuntimeError(f'Could not find metadata in bag directory {path}') from None
        except ValueError as err:
            raise RuntimeError(str(err)) from None
        return _mcap_info(mcap_path)
    try:
        resolve_recording(path)
    except ValueError:
        raise RuntimeError(f'No plugin detected that could open file {path} (it is not an '
                           'MCAP file)') from None
    return _mcap_info(path)


def _folder_info(folder: str) -> BagInfo:
    """rosbag2's MetadataIo::read_metadata: metadata.yaml, and the folder's size."""
    meta_path = os.path.join(folder, BAG_METADATA_FILE)
    try:
        with open(meta_path) as f:
            m = yaml.safe_load(f)['rosbag2_bagfile_information']
        version = int(m['version'])
        topics = [TopicInformation(str(t['topic_metadata']['name']),
                                   str(t['topic_metadata']['type']),
                                   str(t['topic_metadata']['serialization_format']),
                                   int(t['message_count']))
                  for t in m['topics_with_message_count'] or []]
        names = [str(p) for p in m['relative_file_paths'] or []]
        info = BagInfo(
            relative_file_paths=names, bag_size=0,
            storage_identifier=str(m['storage_identifier']),
            ros_distro=str(m.get('ros_distro') or '') if version >= 8 else '',
            starting_time=int(m['starting_time']['nanoseconds_since_epoch']),
            duration=int(m['duration']['nanoseconds']),
            message_count=int(m['message_count']), topics_with_message_count=topics,
            files=[os.path.join(folder, os.path.basename(p)) for p in names])
    except (yaml.YAMLError, KeyError, TypeError, ValueError) as err:
        why = ' '.join(str(err).split())
        raise RuntimeError(f'Exception on parsing info file: {meta_path}: {why}') from None
    info.bag_size = sum(entry.stat(follow_symlinks=False).st_size
                        for entry in os.scandir(folder) if entry.is_file(follow_symlinks=False))
    return info


def _mcap_info(path: str) -> BagInfo:
    """The mcap storage plugin's read_metadata: the summary, else a scan of the records."""
    with open(path, 'rb') as f:
        reader = make_reader(f)
        try:
            summary = reader.get_summary()
            records = list(reader.iter_metadata()) if summary else []
        except (McapError, ValueError, EOFError, OSError, struct.error):
            summary = None      # no footer (shorter than one, even): the writer did not finish
    if summary is None or summary.statistics is None:
        return _scanned_info(path)
    stats = summary.statistics
    topics = [TopicInformation(c.topic, _schema_name(summary.schemas, c.schema_id),
                               c.message_encoding, stats.channel_message_counts.get(i, 0))
              for i, c in sorted(summary.channels.items())]
    bag_records = [r.metadata for r in records if r.name == BAG_METADATA_NAME]
    return BagInfo([path], os.path.getsize(path), 'mcap', _ros_distro(bag_records),
                   stats.message_start_time,
                   stats.message_end_time - stats.message_start_time, stats.message_count,
                   topics, [path])


def _scanned_info(path: str) -> BagInfo:
    """An MCAP file without summary, counted from its complete records (mcap's fallback scan:
    a record cut by the end of the file is an error)."""
    cut = _cut_record(path)
    if cut is not None:
        raise RuntimeError(f'{path} is cut short: its record at byte {cut} runs past the end of '
                           f'the file ({os.path.getsize(path)} bytes)')
    try:
        recording = read_recording(path)
    except (ValueError, KeyError, struct.error) as err:    # a record with garbage in it
        raise RuntimeError(f'{path} is not a readable MCAP file: {err}') from None
    times = [m.log_time for m in recording.messages]
    start, end = (min(times), max(times)) if times else (0, 0)
    topics = [TopicInformation(t.name, t.type_name, t.message_encoding, t.count)
              for t in recording.topics.values()]
    bag_records = [recording.metadata[BAG_METADATA_NAME]] \
        if BAG_METADATA_NAME in recording.metadata else []
    return BagInfo([path], os.path.getsize(path), 'mcap', _ros_distro(bag_records), start,
                   end - start, len(times), topics, [path], scanned=True)


def _cut_record(path: str) -> Optional[int]:
    """Offset of the record of MCAP file `path` that runs past the end of the file, None if the
    file ends where a record ends (or with a footer). Walks the record headers (opcode, uint64
    length) from the end of the magic."""
    size = os.path.getsize(path)
    with open(path, 'rb') as f:
        pos = 8
        while pos < size:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9 or pos + 9 + int.from_bytes(head[1:], 'little') > size:
                return pos
            if head[0] == FOOTER_OPCODE:
                return None
            pos += 9 + int.from_bytes(head[1:], 'little')
    return None


def _schema_name(schemas: Dict[int, object], schema_id: int) -> str:
    schema = schemas.get(schema_id)
    return schema.name if schema is not None else ''


def _ros_distro(records: Sequence[Dict[str, str]]) -> str:
    """The distro the ``rosbag2`` metadata records name, the last one winning (rosbag2 decodes
    each in turn; metadata before version 8 has none)."""
    distro = ''
    for record in records:
        text = record.get('serialized_metadata', '')
        if text:
            try:
                metadata = yaml.safe_load(text)
            except yaml.YAMLError as err:
                raise RuntimeError(f'bad rosbag2 metadata record: {" ".join(str(err).split())}'
                                   ) from None
            if int(metadata.get('version', 0)) >= 8:
                distro = str(metadata.get('ros_distro') or '')
        distro = record.get('ROS_DISTRO', distro)
    return distro


def stored_bag_metadata(path: str) -> str:
    """The bag metadata YAML of the last ``rosbag2`` record of finished MCAP file `path` (what
    its writer wrote when it closed); '' if it has none."""
    with open(path, 'rb') as f:
        records = [r for r in make_reader(f).iter_metadata() if r.name == BAG_METADATA_NAME]
    return records[-1].metadata.get('serialized_metadata', '') if records else ''


def _service_list(info: BagInfo) -> List[ServiceInformation]:
    """The services whose event topics the bag holds, with their event counts."""
    return [ServiceInformation(t.name[:-len(SERVICE_EVENT_SUFFIX)],
                               t.type[:-len(EVENT_TYPE_SUFFIX)], t.serialization_format,
                               t.message_count)
            for t in info.topics_with_message_count if is_service_event_topic(t.name, t.type)]


def count_service_requests(info: BagInfo) -> List[ServiceInformation]:
    """The services of the bag with their request and response counts, as ``ros2 bag info -v``
    (rosbag2_cpp::Info::read_service_info): the distinct (client gid, sequence number) pairs of
    the events REQUEST_SENT/RECEIVED and RESPONSE_SENT/RECEIVED. The events' ServiceEventInfo
    is deserialized from the start of each message, as rosbag2 does (rclpy, imported here)."""
    services = _service_list(info)
    if not services:
        return services
    from rclpy.serialization import deserialize_message
    from service_msgs.msg import ServiceEventInfo
    topics = {s.name + SERVICE_EVENT_SUFFIX: s for s in services}
    seen: Dict[str, Tuple[Set[Tuple[bytes, int]], Set[Tuple[bytes, int]]]] = {
        t: (set(), set()) for t in topics}
    requests = {ServiceEventInfo.REQUEST_SENT, ServiceEventInfo.REQUEST_RECEIVED}
    responses = {ServiceEventInfo.RESPONSE_SENT, ServiceEventInfo.RESPONSE_RECEIVED}
    for path in info.files:
        for message in read_recording(path).messages:
            if message.topic in topics:
                event = deserialize_message(message.data, ServiceEventInfo)
                key = (bytes(event.client_gid), event.sequence_number)
                if event.event_type in requests:
                    seen[message.topic][0].add(key)
                elif event.event_type in responses:
                    seen[message.topic][1].add(key)
    for topic, service in topics.items():
        service.request_count, service.response_count = map(len, seen[topic])
    return services


def format_duration(ns: int) -> Tuple[str, str, str]:
    """(date, time, seconds) of a time or duration `ns` >= 0 as rosbag2 prints them:
    'Apr  9 2020', '06:27:36.763032325' (local time) and '1586406456.763032325'."""
    seconds, rest = divmod(ns, 10 ** 9)
    fraction = f'{rest:09d}'
    local = time.localtime(seconds)
    return (time.strftime('%b %e %Y', local), f'{time.strftime("%H:%M:%S", local)}.{fraction}',
            f'{seconds}.{fraction}')


def format_time_point(ns: int) -> str:
    """'Apr  9 2020 06:27:36.763032325 (1586406456.763032325)'."""
    date, clock, seconds = format_duration(ns)
    return f'{date} {clock} ({seconds})'


def format_file_size(size: int) -> str:
    """'512 B', '44.5 KiB', ...: powers of 1024, one decimal above bytes."""
    value, index = float(size), 0
    units = ('B', 'KiB', 'MiB', 'GiB', 'TiB')
    while value >= 1024 and index < 4:
        value /= 1024
        index += 1
    return f'{value:.{0 if index == 0 else 1}f} {units[index]}'


def _lines(first: str, items: Sequence[str], indent: int) -> str:
    """`first` then each item on a line, the first one after `first`, the others indented."""
    if not items:
        return first + '\n'
    return first + items[0] + '\n' + ''.join(' ' * indent + i + '\n' for i in items[1:])


def format_bag_metadata(info: BagInfo, only_topic: bool = False) -> str:
    """rosbag2_py::format_bag_meta_data: what ``ros2 bag info`` prints (plus print's newline).

    `only_topic` leaves out the Service lines (the first part of ``-v``'s output)."""
    services = _service_list(info)
    ros_distro = info.ros_distro or 'unknown'
    topics = [f'Topic: {t.name} | Type: {t.type} | Count: {t.message_count} | '
              f'Serialization Format: {t.serialization_format}'
              for t in info.topics_with_message_count
              if not is_service_event_topic(t.name, t.type)]
    text = ('\n' + _lines('Files:             ', info.relative_file_paths, INDENT)
            + f'Bag size:          {format_file_size(info.bag_size)}\n'
            f'Storage id:        {info.storage_identifier}\n'
            f'ROS Distro:        {ros_distro}\n'
            f'Duration:          {format_duration(info.duration)[2]}s\n'
            f'Start:             {format_time_point(info.starting_time)}\n'
            f'End:               {format_time_point(info.starting_time + info.duration)}\n'
            f'Messages:          '
            f'{info.message_count - sum(s.event_count for s in services)}\n'
            + _lines('Topic information: ', topics, INDENT))
    if not only_topic:
        text += f'Service:           {len(services)}\nService information: '
        if services:
            text += _lines('', [f'Service: {s.name} | Type: {s.type} | Event Count: '
                                f'{s.event_count} | Serialization Format: '
                                f'{s.serialization_format}' for s in services], INDENT + 2)
    return text


def format_service_info(services: Sequence[ServiceInformation]) -> str:
    """rosbag2_py::format_service_info: the Service lines of ``ros2 bag info -v``."""
    head = f'Service:           {len(services)}\nService information: '
    if not services:
        return head
    return _lines(head, [f'Service: {s.name} | Type: {s.type} | Request Count: '
                         f'{s.request_count} | Response Count: {s.response_count} | '
                         f'Serialization Format: {s.serialization_format}' for s in services],
                  len('Service information: '))
