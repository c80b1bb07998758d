"""Parameters of the Foxglove live-view node, declared once on the fields of
:class:`FoxgloveConfig`.

No rclpy. The node declares :data:`PARAMETERS` through the shared runtime and hands the values
to :func:`parse_params`; a bad value is one error line and exit status 2. The orchestrator
checks a port given to ``run_experiment.py --foxglove`` with :meth:`FoxgloveConfig.validate`.
"""
from dataclasses import dataclass
from typing import Dict, Mapping, Tuple

from metampc_common.params import (build, check_fields, param, ParameterError, ParamSpec,
                                   Section, table, Value)

DEFAULT_PORT = 8765     # the Foxglove app's default for a WebSocket connection


@dataclass
class FoxgloveConfig:
    """Everything the live-view node is configured with (each field is a parameter)."""

    host: str = param('127.0.0.1', 'address to serve on: 127.0.0.1 this machine only, '
                                   '0.0.0.0 every interface (no authentication)')
    port: int = param(DEFAULT_PORT, 'TCP port of the WebSocket server (0: a free one, logged)',
                      ge=0, le=65535)
    topics: Tuple[str, ...] = param((), 'topics to serve (relative names resolve in the node '
                                        'namespace); empty: every topic of the namespace, '
                                        'served as it appears', item=str)
    discovery_period: float = param(0.5, 'wall time, s, between two looks for new topics',
                                    gt=0)
    qos_depth: int = param(100, 'keep_last depth of the subscriptions', ge=1)

    def __post_init__(self):
        self.topics = tuple(self.topics)

    def validate(self) -> None:
        """Every field within its rule, an address, topic names."""
        check_fields(self)
        if not self.host:
            raise ValueError('host must be an address, e.g. 127.0.0.1 or 0.0.0.0')
        if not all(self.topics):
            raise ValueError(f'topics must be topic names, got {list(self.topics)!r}')


SECTION = Section(FoxgloveConfig)
PARAMETERS: Dict[str, ParamSpec] = table([SECTION])


def parse_params(values: Mapping[str, Value]) -> FoxgloveConfig:
    """Raw parameter values (as ROS gives them) -> a checked :class:`FoxgloveConfig`.

    Raises:
        ParameterError: naming the first parameter of the wrong type or out of range.
    """
    return build(SECTION, values)


__all__ = ['DEFAULT_PORT', 'FoxgloveConfig', 'PARAMETERS', 'parse_params', 'ParameterError']
