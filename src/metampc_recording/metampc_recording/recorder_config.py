"""Parameters of the recorder node, declared once on the fields of :class:`RecorderConfig`.

No rclpy. The node declares :data:`PARAMETERS` through the shared runtime
(:func:`metampc_common.node_main.declare_parameters`) and hands the values to
:func:`parse_params`; a bad value is one error line and exit status 2
(:class:`~metampc_common.params.ParameterError`). The orchestrator builds a
:class:`RecorderConfig` and turns it into ``--ros-args`` with :meth:`RecorderConfig.to_parameters`.
"""
import json
from dataclasses import dataclass
from typing import Dict, Mapping, Tuple

from metampc_common.params import (build, param, ParameterError, ParamSpec, Section, table,
                                   Value)
from metampc_recording.mcap_writer import COMPRESSIONS, McapWriterConfig

MIB = 1024 * 1024


@dataclass
class RecorderConfig:
    """Everything the recorder node is configured with (each field is a parameter)."""

    output: str = param('', 'MCAP file to create (required; parent folders are created; an '
                            'existing file is an error)')
    topics: Tuple[str, ...] = param((), 'topics to record (relative names resolve in the node '
                                        'namespace); empty: every topic of the namespace, '
                                        'subscribed as it appears', item=str)
    record_clock: bool = param(False, 'also record /clock')
    chunk_size: int = param(MIB, 'uncompressed bytes per MCAP chunk', ge=1)
    compression: str = param('lz4', 'chunk compression', choices=sorted(COMPRESSIONS))
    metadata_json: str = param('{}', "the run's configuration, a JSON object, stored in the "
                                     "'metampc' metadata record")
    discovery_period: float = param(0.25, 'wall time, s, between two looks for new topics',
                                    gt=0)
    flush_period: float = param(1.0, 'wall time, s, after which an open chunk is written '
                                     '(0: only when full)', ge=0)
    qos_depth: int = param(0, 'keep_last depth of the recording subscriptions (0: keep_all, '
                              'so that a held-back publisher loses nothing)', ge=0)

    def __post_init__(self):
        self.topics = tuple(self.topics)

    def validate(self) -> None:
        """What the ranges cannot say: an output, topic names, a JSON object."""
        if not self.output:
            raise ValueError('output (the MCAP file to write) is required')
        if not all(self.topics):
            raise ValueError(f'topics must be topic names, got {list(self.topics)!r}')
        try:
            run_config = json.loads(self.metadata_json)
        except json.JSONDecodeError as err:
            raise ValueError(f'metadata_json is not JSON: {err}') from None
        if not isinstance(run_config, dict):
            raise ValueError(f'metadata_json must be a JSON object, got {self.metadata_json!r}')

    def to_parameters(self) -> Dict[str, object]:
        """ROS parameters of the node, for :func:`metampc_recording.processes.ros_args` (which
        quotes strings, so rcl reads ``metadata_json`` as a string, not a YAML map).

        Empty `topics` is left out: an empty list has no type on the command line.
        """
        params: Dict[str, object] = dict(vars(self), topics=list(self.topics))
        if not self.topics:
            del params['topics']
        return params

    def writer_config(self) -> McapWriterConfig:
        """The MCAP writer's options (the config is checked by :func:`parse_params`)."""
        return McapWriterConfig(self.output, self.chunk_size, self.compression,
                                json.loads(self.metadata_json))


SECTION = Section(RecorderConfig)
PARAMETERS: Dict[str, ParamSpec] = table([SECTION])


def parse_params(values: Mapping[str, Value]) -> RecorderConfig:
    """Raw parameter values (as ROS gives them) -> a checked :class:`RecorderConfig`.

    Raises:
        ParameterError: naming the first parameter of the wrong type or out of range.
    """
    return build(SECTION, values)


__all__ = ['MIB', 'RecorderConfig', 'PARAMETERS', 'parse_params', 'ParameterError']
