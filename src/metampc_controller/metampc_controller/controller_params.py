"""Parameters of the `controller` node: names, defaults, units, parsing and range checks.

Pure Python (no rclpy). The node declares every entry of :data:`PARAMETERS`, hands the values
to :func:`parse_params` and exits with one error line (status 2) if that raises
:class:`ParameterError`.
"""
import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Tuple

from metampc_common.params import number, ParameterError, ParamSpec, Value

from metampc_controller.excitation import ExcitationConfig
from metampc_controller.mpc import MpcConfig
from metampc_controller.nmpc import N_Y
from metampc_controller.references import make_reference, PaperConfig

PLANNERS = ('latent_mpc', 'nmpc')
PRE_MODEL_INPUTS = ('zero', 'excitation')
# Excitation kinds whose signal is generated block by block (see controller_core): multisine
# normalises its peak over the generated length, so blocks of it would not join up.
EXCITATION_KINDS = ('random_hold', 'prbs')
REFERENCE_KINDS = ('paper', 'setpoint', 'steps', 'sine')
# Upper bound of the encoder history H the node accepts: the paper's H is ~10, and the history
# buffer (2 x MAX_HISTORY samples) is allocated at start.
MAX_HISTORY = 1000

_MPC = MpcConfig()
_PAPER = PaperConfig()

PARAMETERS: Dict[str, ParamSpec] = {
    'rate_hz': ParamSpec(10.0, 'tick rate on the node clock, Hz (> 0; sim time under a '
                               'lockstep plant: set it to 1/dt)'),
    'horizon': ParamSpec(_MPC.horizon, 'MPC horizon N, samples (integer >= 1)'),
    'q': ParamSpec(list(_MPC.q), 'output tracking weights Q = diag(q), one per plant output '
                                 '(>= 0; the default tracks x1 only)'),
    'r': ParamSpec(_MPC.r, 'Delta-u weight (> 0)'),
    'u_min': ParamSpec(_MPC.u_min, 'input lower bound (finite, <= u_max)'),
    'u_max': ParamSpec(_MPC.u_max, 'input upper bound (finite, >= u_min)'),
    'planner': ParamSpec('latent_mpc', "'latent_mpc' (eq. mpc on the NSSM) or 'nmpc' (true-model "
                                       "yardstick, theta from plant_info)"),
    'reference': ParamSpec('paper', "reference kind: 'paper', 'setpoint', 'steps' or 'sine'"),
    'reference_outputs': ParamSpec([0], 'indices of the outputs that follow the reference'),
    'reference_values': ParamSpec([], "paper: set-points (default the paper's "
                                      f"{list(_PAPER.setpoints)}); setpoint: one value "
                                      "(default 0); steps: the value from each time on"),
    'reference_times': ParamSpec([], 'steps: increasing times, s since the plant reset'),
    'reference_initial': ParamSpec(0.0, 'steps: value before the first time'),
    'reference_segment': ParamSpec(_PAPER.segment, 'paper: seconds per set-point (> 0)'),
    'reference_start': ParamSpec(_PAPER.start, 'paper: start of the first set-point\'s segment, '
                                               's (that set-point also holds before it)'),
    'reference_amplitude': ParamSpec(0.5, 'sine: amplitude'),
    'reference_period': ParamSpec(10.0, 'sine: period, s (> 0)'),
    'reference_offset': ParamSpec(0.0, 'sine: offset'),
    'reference_phase': ParamSpec(0.0, 'sine: phase, rad'),
    'pre_model_input': ParamSpec('zero', "input before a model: 'zero' or 'excitation' "
                                         "(seeded, within the bounds)"),
    'excitation_kind': ParamSpec('random_hold', "'random_hold' (uniform levels) or 'prbs'"),
    'excitation_amplitude': ParamSpec(1.0, 'excitation within [-a, a] and the bounds (> 0)'),
    'excitation_hold_s': ParamSpec(0.5, 'excitation hold time, s (> 0)'),
    'excitation_seed': ParamSpec(0, 'excitation seed (integer >= 0)'),
    'max_iter': ParamSpec(_MPC.max_iter, 'OSQP iteration cap (integer >= 1)'),
    'time_limit': ParamSpec(_MPC.time_limit, 'OSQP wall-time cap per solve, s (> 0)'),
    'eps_abs': ParamSpec(_MPC.eps_abs, 'OSQP absolute tolerance (> 0)'),
    'eps_rel': ParamSpec(_MPC.eps_rel, 'OSQP relative tolerance (>= 0)'),
    'history': ParamSpec(0, 'required encoder history H of the weights (0: any H up to '
                            f'{MAX_HISTORY})'),
    'active': ParamSpec(True, 'publish inputs from the start (service set_active toggles)'),
}


@dataclass
class ControllerConfig:
    """Everything the controller node is configured with.

    Attributes:
        rate_hz: tick rate on the node clock, Hz.
        mpc: latent MPC settings (horizon, weights, bounds, OSQP); also the NMPC's horizon,
            weights and bounds.
        n_y: plant outputs (= len(mpc.q)); n_u is 1 (the van der Pol plant).
        planner: 'latent_mpc' or 'nmpc'.
        reference_kind, reference_params: arguments of references.make_reference.
        pre_model_input: 'zero' or 'excitation'.
        excitation: the pre-model excitation (kind, bounds = [u_min, u_max] within the
            amplitude, hold_s).
        excitation_seed: its seed.
        history: required H of the weights, 0 for any up to MAX_HISTORY.
        active: publish inputs from the start.
    """

    rate_hz: float = 10.0
    mpc: MpcConfig = field(default_factory=MpcConfig)
    n_y: int = N_Y
    planner: str = 'latent_mpc'
    reference_kind: str = 'paper'
    reference_params: Dict[str, Any] = field(default_factory=dict)
    pre_model_input: str = 'zero'
    excitation: ExcitationConfig = field(default_factory=ExcitationConfig)
    excitation_seed: int = 0
    history: int = 0
    active: bool = True


def _numbers(name: str, value: Value, integer: bool = False) -> List:
    """A list parameter as numbers; ParameterError naming `name` otherwise."""
    if isinstance(value, (str, bytes, bool)) or not hasattr(value, '__len__'):
        raise ParameterError(f'{name} must be a list of numbers, got {value!r}')
    return [number(name, v, integer) for v in value]


def _choice(name: str, value: Value, choices: Tuple[str, ...]) -> str:
    if value not in choices:
        raise ParameterError(f'{name} must be one of {", ".join(choices)}, got {value!r}')
    return value


def _reference(values: Mapping[str, Value], num: Mapping[str, float], n_y: int
               ) -> Tuple[str, Dict[str, Any]]:
    """(kind, make_reference arguments) from the reference_* parameters."""
    kind = _choice('reference', values['reference'], REFERENCE_KINDS)
    outputs = tuple(_numbers('reference_outputs', values['reference_outputs'], integer=True))
    refs = _numbers('reference_values', values['reference_values'])
    times = _numbers('reference_times', values['reference_times'])
    params: Dict[str, Any] = {'n_y': n_y, 'outputs': outputs}
    if kind == 'paper':
        params.update(setpoints=tuple(refs) or _PAPER.setpoints,
                      segment=num['reference_segment'], start=num['reference_start'])
    elif kind == 'setpoint':
        if len(refs) > 1:
            raise ParameterError(f'reference setpoint takes one value in reference_values, '
                                 f'got {refs}')
        params['value'] = refs[0] if refs else 0.0
    elif kind == 'steps':
        if not refs or len(refs) != len(times):
            raise ParameterError('reference steps needs reference_times and reference_values '
                                 f'of the same non-zero length, got {times} and {refs}')
        params.update(steps=tuple(zip(times, refs)), initial=num['reference_initial'])
    else:
        params.update(amplitude=num['reference_amplitude'], period=num['reference_period'],
                      offset=num['reference_offset'], phase=num['reference_phase'])
    try:
        make_reference(kind, **params)
    except ValueError as err:
        raise ParameterError(f'reference {kind}: {err}') from None
    return kind, params


def parse_params(values: Mapping[str, Value]) -> ControllerConfig:
    """Turn raw parameter values (as ROS gives them) into a checked :class:`ControllerConfig`.

    Raises:
        ParameterError: naming the first parameter that is of the wrong type or out of range.
    """
    num = {name: number(name, values[name], integer=isinstance(spec.default, int))
           for name, spec in PARAMETERS.items()
           if isinstance(spec.default, (int, float)) and not isinstance(spec.default, bool)}
    for name in num:
        if not math.isfinite(num[name]):
            raise ParameterError(f'{name} must be finite, got {num[name]}')
    if not num['rate_hz'] > 0:
        raise ParameterError(f'rate_hz must be > 0 Hz, got {num["rate_hz"]}')
    q = _numbers('q', values['q'])
    if not q:
        raise ParameterError('q needs one weight per plant output, got []')
    planner = _choice('planner', values['planner'], PLANNERS)
    if planner == 'nmpc' and len(q) != N_Y:
        raise ParameterError(f'planner nmpc needs {N_Y} weights in q (the van der Pol '
                             f'outputs), got {q}')
    for name in ('eps_abs', 'time_limit'):
        if not num[name] > 0:
            raise ParameterError(f'{name} must be > 0, got {num[name]}')
    if not 0 <= num['history'] <= MAX_HISTORY:
        raise ParameterError(f'history must be in [0, {MAX_HISTORY}] (0: any), got '
                             f'{num["history"]}')
    if num['excitation_seed'] < 0:
        raise ParameterError(f'excitation_seed must be >= 0, got {num["excitation_seed"]}')
    try:
        mpc = MpcConfig(horizon=num['horizon'], q=tuple(q), r=num['r'], u_min=num['u_min'],
                        u_max=num['u_max'], max_iter=num['max_iter'],
                        time_limit=num['time_limit'], eps_abs=num['eps_abs'],
                        eps_rel=num['eps_rel'])
    except ValueError as err:
        raise ParameterError(str(err)) from None
    amplitude = num['excitation_amplitude']
    if not amplitude > 0:
        raise ParameterError(f'excitation_amplitude must be > 0, got {amplitude}')
    excitation = ExcitationConfig(
        kind=_choice('excitation_kind', values['excitation_kind'], EXCITATION_KINDS),
        u_min=max(mpc.u_min, -amplitude), u_max=min(mpc.u_max, amplitude),
        hold_s=num['excitation_hold_s'])
    try:
        excitation.validate()
    except ValueError as err:
        raise ParameterError(f'excitation: {err} (bounds are [u_min, u_max] within '
                             '+-excitation_amplitude)') from None
    kind, reference_params = _reference(values, num, len(q))
    active = values['active']
    if not isinstance(active, bool):
        raise ParameterError(f'active must be true or false, got {active!r}')
    return ControllerConfig(
        rate_hz=num['rate_hz'], mpc=mpc, n_y=len(q), planner=planner, reference_kind=kind,
        reference_params=reference_params,
        pre_model_input=_choice('pre_model_input', values['pre_model_input'],
                                PRE_MODEL_INPUTS),
        excitation=excitation, excitation_seed=num['excitation_seed'],
        history=num['history'], active=active)
