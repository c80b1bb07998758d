"""Parameters of the `plant` node: names, defaults, units, parsing and range checks.

Pure Python (no rclpy), so the checks are testable alone. The node declares every entry of
:data:`PARAMETERS`, hands the values to :func:`parse_params` and exits with one error line if
that raises :class:`ParameterError`.
"""
import math
from dataclasses import dataclass, field
from typing import Dict, Mapping

from metampc_common.params import number, ParameterError, ParamSpec, Value
from metampc_plant.vanderpol import N_X, VdpConfig

MODES = ('lockstep', 'realtime')


_VDP = VdpConfig()

PARAMETERS: Dict[str, ParamSpec] = {
    'theta': ParamSpec(_VDP.theta, 'van der Pol damping, dimensionless (finite)'),
    'dt': ParamSpec(_VDP.dt, 'sample time, s (> 0)'),
    'substeps': ParamSpec(_VDP.substeps, 'RK4 steps per sample (integer >= 1)'),
    'x0': ParamSpec(list(_VDP.x0), 'initial state [x1, x2] (finite, inside state_bound)'),
    'u_min': ParamSpec(_VDP.u_min, 'input lower bound (finite, <= u_max)'),
    'u_max': ParamSpec(_VDP.u_max, 'input upper bound (finite, >= u_min)'),
    'process_noise_std': ParamSpec(_VDP.process_noise_std,
                                   'std of the noise added to x2 per sample, times sqrt(dt)'),
    'measurement_noise_std': ParamSpec(_VDP.measurement_noise_std,
                                       'std of the noise added to each output (>= 0)'),
    'seed': ParamSpec(_VDP.seed, 'noise seed (integer >= 0)'),
    'state_bound': ParamSpec(_VDP.state_bound,
                             'the plant is declared diverged when |x|_inf exceeds this (> 0)'),
    'mode': ParamSpec('lockstep', "clock mode: 'lockstep' (step per answered input, publishes "
                                  "/clock) or 'realtime' (wall-clock timer)"),
    'rate_hz': ParamSpec(0.0, 'realtime sample rate, Hz (> 0; 0: 1/dt, i.e. real time)'),
    'publish_clock': ParamSpec(True, 'lockstep only: publish /clock (sim time) for '
                                     'use_sim_time nodes'),
    'input_timeout': ParamSpec(1.0, 'lockstep: wall time, s, to wait for the input answering '
                                    'a step before holding the last one (0: wait forever)'),
    'start_timeout': ParamSpec(10.0, 'lockstep: wall time, s, to wait for a subscriber on y '
                                     'and a publisher on u before publishing y_0 anyway '
                                     '(0: wait forever)'),
}


@dataclass
class PlantNodeConfig:
    """Everything the plant node is configured with.

    Attributes:
        vdp: the simulated plant (see :class:`VdpConfig`).
        mode: 'lockstep' or 'realtime'.
        rate_hz: realtime sample rate, Hz (resolved: never 0).
        publish_clock: lockstep only: publish /clock.
        input_timeout: lockstep: wall time, s, before a step proceeds with the held input;
            0 waits forever.
        start_timeout: lockstep: wall time, s, to wait for a controller (a subscriber on y
            and a publisher on u) before the first step; 0 waits forever. It covers the
            controller's start-up and DDS discovery, which took up to ~4 s here.
    """

    vdp: VdpConfig = field(default_factory=VdpConfig)
    mode: str = 'lockstep'
    rate_hz: float = 10.0
    publish_clock: bool = True
    input_timeout: float = 1.0
    start_timeout: float = 10.0


def parse_params(values: Mapping[str, Value]) -> PlantNodeConfig:
    """Turn raw parameter values (as ROS gives them) into a checked :class:`PlantNodeConfig`.

    Raises:
        ParameterError: naming the first parameter that is of the wrong type or out of range.
    """
    num = {name: number(name, values[name], integer=isinstance(spec.default, int))
           for name, spec in PARAMETERS.items()
           if isinstance(spec.default, (int, float)) and not isinstance(spec.default, bool)}
    x0 = values['x0']
    if isinstance(x0, (str, bool)) or not hasattr(x0, '__len__') or len(x0) != N_X:
        raise ParameterError(f'x0 must be a list of {N_X} numbers, got {x0!r}')
    x0 = tuple(number('x0', v) for v in x0)
    vdp = VdpConfig(theta=num['theta'], dt=num['dt'], substeps=num['substeps'], x0=x0,
                    u_min=num['u_min'], u_max=num['u_max'],
                    process_noise_std=num['process_noise_std'],
                    measurement_noise_std=num['measurement_noise_std'],
                    state_bound=num['state_bound'], seed=num['seed'])
    try:
        vdp.validate()
    except ValueError as err:
        raise ParameterError(str(err)) from None
    if max(abs(v) for v in x0) > vdp.state_bound:
        raise ParameterError(f'x0 {list(x0)} lies outside state_bound {vdp.state_bound}')
    mode = values['mode']
    if mode not in MODES:
        raise ParameterError(f'mode must be one of {", ".join(MODES)}, got {mode!r}')
    rate_hz = num['rate_hz']
    if not (rate_hz >= 0 and math.isfinite(rate_hz)):
        raise ParameterError(f'rate_hz must be >= 0 Hz (0: 1/dt), got {rate_hz}')
    for name in ('input_timeout', 'start_timeout'):
        if not (num[name] >= 0 and math.isfinite(num[name])):
            raise ParameterError(f'{name} must be >= 0 s (0: wait forever), got {num[name]}')
    publish_clock = values['publish_clock']
    if not isinstance(publish_clock, bool):
        raise ParameterError(f'publish_clock must be true or false, got {publish_clock!r}')
    return PlantNodeConfig(vdp=vdp, mode=mode, rate_hz=rate_hz or 1.0 / vdp.dt,
                           publish_clock=publish_clock, input_timeout=num['input_timeout'],
                           start_timeout=num['start_timeout'])
