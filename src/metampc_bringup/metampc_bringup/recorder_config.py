"""Parameters of the recorder node: table, typed config and checks. No rclpy.

The node declares every entry of :data:`PARAMETERS` through the shared runtime
(:func:`metampc_common.node_main.declare_parameters`) and hands the values to
:func:`parse_params`; a bad value is one error line and exit status 2
(:class:`~metampc_common.params.ParameterError`). The orchestrator builds a
:class:`RecorderConfig` and turns it into ``--ros-args`` with :meth:`RecorderConfig.to_parameters`.
"""
import json
import math
from dataclasses import dataclass, field
from typing import Dict, List, Mapping

from metampc_common.params import number, ParameterError, ParamSpec, Value

from .mcap_writer import COMPRESSIONS, McapWriterConfig

MIB = 1024 * 1024


@dataclass
class RecorderConfig:
    """Everything the recorder node is configured with (see :data:`PARAMETERS`).

    Attributes:
        output: MCAP file to create (required; an existing file is an error).
        topics: topics to record; empty: every topic of the node's namespace, as it appears.
        record_clock: also record ``/clock``.
        chunk_size: uncompressed bytes per MCAP chunk (>= 1).
        compression: 'zstd', 'lz4' or 'none'.
        metadata_json: the run's configuration, a JSON object (stored in the ``metampc``
            metadata record).
        discovery_period: s between two looks at the graph for new topics (> 0).
        flush_period: s after which an open chunk is closed and written (0: only when full).
        qos_depth: keep_last depth of the recording subscriptions (>= 1).
    """

    output: str = ''
    topics: List[str] = field(default_factory=list)
    record_clock: bool = False
    chunk_size: int = MIB
    compression: str = 'lz4'
    metadata_json: str = '{}'
    discovery_period: float = 0.25
    flush_period: float = 1.0
    qos_depth: int = 1000

    def to_parameters(self) -> Dict[str, object]:
        """ROS parameters of the node, for :func:`metampc_bringup.processes.ros_args` (which
        quotes strings, so rcl reads ``metadata_json`` as a string, not a YAML map).

        Empty `topics` is left out: an empty list has no type on the command line.
        """
        params: Dict[str, object] = dict(vars(self))
        if not self.topics:
            del params['topics']
        return params

    def writer_config(self) -> McapWriterConfig:
        """The MCAP writer's options (the config is checked by :func:`parse_params`)."""
        return McapWriterConfig(self.output, self.chunk_size, self.compression,
                                json.loads(self.metadata_json))


_DEFAULT = RecorderConfig()
PARAMETERS: Dict[str, ParamSpec] = {
    'output': ParamSpec(_DEFAULT.output, 'MCAP file to create (required; parent folders are '
                                         'created; an existing file is an error)'),
    'topics': ParamSpec([], 'topics to record (relative names resolve in the node namespace); '
                            'empty: every topic of the namespace, subscribed as it appears'),
    'record_clock': ParamSpec(_DEFAULT.record_clock, 'also record /clock'),
    'chunk_size': ParamSpec(_DEFAULT.chunk_size, 'uncompressed bytes per MCAP chunk (>= 1)'),
    'compression': ParamSpec(_DEFAULT.compression, 'chunk compression: '
                                                   + ', '.join(sorted(COMPRESSIONS))),
    'metadata_json': ParamSpec(_DEFAULT.metadata_json, "the run's configuration, a JSON object, "
                                                       "stored in the 'metampc' metadata record"),
    'discovery_period': ParamSpec(_DEFAULT.discovery_period,
                                  'wall time, s, between two looks for new topics (> 0)'),
    'flush_period': ParamSpec(_DEFAULT.flush_period, 'wall time, s, after which an open chunk '
                                                     'is written (0: only when full)'),
    'qos_depth': ParamSpec(_DEFAULT.qos_depth, 'keep_last depth of the recording '
                                               'subscriptions (>= 1)'),
}


def _positive(name: str, value: float, zero_ok: bool = False) -> float:
    if not math.isfinite(value) or value < 0 or (value == 0 and not zero_ok):
        bound = '>= 0' if zero_ok else '> 0'
        raise ParameterError(f'{name} must be {bound}, got {value}')
    return value


def parse_params(values: Mapping[str, Value]) -> RecorderConfig:
    """Raw parameter values (as ROS gives them) -> a checked :class:`RecorderConfig`.

    Raises:
        ParameterError: naming the first parameter of the wrong type or out of range.
    """
    output = values['output']
    if not isinstance(output, str) or not output:
        raise ParameterError('output (the MCAP file to write) is required')
    topics = values['topics'] or []     # the empty default is declared as a byte array
    if not isinstance(topics, list) or not all(isinstance(t, str) and t for t in topics):
        raise ParameterError(f'topics must be a list of topic names, got {topics!r}')
    record_clock = values['record_clock']
    if not isinstance(record_clock, bool):
        raise ParameterError(f'record_clock must be true or false, got {record_clock!r}')
    compression = values['compression']
    if compression not in COMPRESSIONS:
        raise ParameterError(f'compression must be one of {", ".join(sorted(COMPRESSIONS))}, '
                             f'got {compression!r}')
    metadata_json = values['metadata_json']
    try:
        run_config = json.loads(metadata_json) if isinstance(metadata_json, str) else None
    except json.JSONDecodeError as err:
        raise ParameterError(f'metadata_json is not JSON: {err}') from None
    if not isinstance(run_config, dict):
        raise ParameterError(f'metadata_json must be a JSON object, got {metadata_json!r}')
    chunk_size = number('chunk_size', values['chunk_size'], integer=True)
    qos_depth = number('qos_depth', values['qos_depth'], integer=True)
    for name, value in (('chunk_size', chunk_size), ('qos_depth', qos_depth)):
        if value < 1:
            raise ParameterError(f'{name} must be >= 1, got {value}')
    return RecorderConfig(
        output=output, topics=list(topics), record_clock=record_clock, chunk_size=chunk_size,
        compression=compression, metadata_json=metadata_json,
        discovery_period=_positive('discovery_period',
                                   number('discovery_period', values['discovery_period'])),
        flush_period=_positive('flush_period', number('flush_period', values['flush_period']),
                               zero_ok=True),
        qos_depth=qos_depth)
