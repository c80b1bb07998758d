"""Parameters of the `plant` node, declared once on the fields of its configs.

Pure Python (no rclpy). The simulated plant's parameters are the fields of
:class:`~metampc_plant.simulator.PlantConfig`, the node's own those of :class:`PlantNodeConfig`
(field metadata: default, description, range; see :mod:`metampc_common.params`). The node
declares :data:`PARAMETERS`, hands the values to :func:`parse_params` and exits with one error
line if that raises :class:`ParameterError`.
"""
from dataclasses import dataclass, field
from typing import Dict, Mapping

from metampc_common.hold_config import HoldConfig
from metampc_common.params import (build, param, ParameterError, ParamSpec, Section, table,
                                   Value)
from metampc_plant.simulator import PlantConfig

MODES = ('lockstep', 'realtime')


@dataclass
class PlantNodeConfig:
    """Everything the plant node is configured with.

    Attributes:
        plant: the simulated plant (see :class:`PlantConfig`), its defaults filled in from its
            family.
        mode: 'lockstep' or 'realtime'.
        rate_hz: realtime sample rate, Hz; 0: 1/dt (see :meth:`sample_rate_hz`).
        publish_clock: lockstep only: publish /clock.
        input_timeout: lockstep: wall time, s, before a step proceeds with the held input;
            0 waits forever.
        start_timeout: lockstep: wall time, s, to wait for a controller (a subscriber on y
            and a publisher on u) before the first step; 0 waits forever. It covers the
            controller's start-up and DDS discovery, which took up to ~4 s here.
        start_subscribers: lockstep: subscribers on y before the first step.
        real_time_factor: lockstep: at most this many times real time, each y no sooner than
            dt / real_time_factor of wall time after the previous one; 0: as fast as the inputs
            answer (see :meth:`pace_s`).
    """

    plant: PlantConfig = field(default_factory=lambda: PlantConfig().resolved())
    mode: str = param('lockstep', 'clock mode: lockstep steps per answered input and publishes '
                                  '/clock, realtime on a wall-clock timer', choices=MODES)
    rate_hz: float = param(0.0, 'realtime sample rate, Hz (0: 1/dt, i.e. real time)', ge=0)
    publish_clock: bool = param(True, 'lockstep only: publish /clock (sim time) for '
                                      'use_sim_time nodes')
    input_timeout: float = param(1.0, 'lockstep: wall time, s, to wait for the input answering '
                                      'a step before holding the last one (0: wait forever)',
                                 ge=0)
    start_timeout: float = param(10.0, 'lockstep: wall time, s, to wait for a subscriber on y '
                                       'and a publisher on u before publishing y_0 anyway '
                                       '(0: wait forever)', ge=0)
    start_subscribers: int = param(1, 'lockstep: subscribers y must have before y_0 goes out '
                                      '(2: the controller and a recorder, so that the recording '
                                      'starts at step 0)', ge=1)
    real_time_factor: float = param(0.0, 'lockstep: run at most this many times real time '
                                         '(1: each y at least dt of wall time after the '
                                         'previous one, a session watched by hand; 0: as fast '
                                         'as the inputs answer)', ge=0)
    hold: HoldConfig = field(default_factory=HoldConfig)

    def pace_s(self) -> float:
        """Lockstep: the least wall time between two y, s (0: none)."""
        return self.plant.dt / self.real_time_factor if self.real_time_factor > 0 else 0.0

    def sample_rate_hz(self) -> float:
        """The realtime rate: rate_hz, or 1/dt when it is 0."""
        return self.rate_hz or 1.0 / self.plant.dt


SECTIONS = (Section(PlantConfig), Section(PlantNodeConfig), Section(HoldConfig))
PARAMETERS: Dict[str, ParamSpec] = table(SECTIONS)


def parse_params(values: Mapping[str, Value]) -> PlantNodeConfig:
    """Turn raw parameter values (as ROS gives them) into a checked :class:`PlantNodeConfig`.

    Raises:
        ParameterError: naming the first parameter that is of the wrong type or out of range.
    """
    plant_section, node_section, hold_section = SECTIONS
    plant = build(plant_section, values).resolved()
    try:
        plant.plant_family.check_theta_in_support(plant.theta)
    except ValueError as err:
        raise ParameterError(f'theta: {err}') from None
    return build(node_section, values, plant=plant, hold=build(hold_section, values))


__all__ = ['MODES', 'PlantNodeConfig', 'SECTIONS', 'PARAMETERS', 'parse_params',
           'ParameterError']
