"""Parameters of the `controller` node, declared once on the fields of its configs.

Pure Python (no rclpy). The MPC's parameters are fields of :class:`MpcConfig`, the reference's
of :class:`ReferenceParams` (prefix ``reference_``), the pre-model excitation's of
:class:`ExcitationParams` (prefix ``excitation_``) and the node's own of
:class:`ControllerConfig` (field metadata: default, description, range; see
:mod:`metampc_common.params`). The node declares :data:`PARAMETERS`, hands the values to
:func:`parse_params` and exits with one error line (status 2) if that raises
:class:`ParameterError`.
"""
from dataclasses import dataclass, field
from typing import Any, Dict, Mapping, Sequence, Tuple

from metampc_common.hold_config import HoldConfig
from metampc_common.params import (build, param, ParameterError, ParamSpec, Section, table,
                                   Value)

from metampc_controller.adaptation_trigger import TriggerConfig
from metampc_common.excitation import amplitude_param, center_param, ExcitationConfig
from metampc_controller.model_check import ModelCheckConfig
from metampc_controller.model_gate import GateConfig
from metampc_controller.mpc import MpcConfig
from metampc_controller.narx_rls import RlsConfig
from metampc_controller.nmpc import SOLVERS as NMPC_SOLVERS
from metampc_controller.planner_registry import REGISTRY
from metampc_controller.references import make_reference, SetpointSequenceConfig

PLANNERS = tuple(REGISTRY)
PRE_MODEL_INPUTS = ('zero', 'excitation')
# Excitation kinds whose signal is generated block by block (see controller_core): multisine
# normalises its peak over the generated length, so blocks of it would not join up.
EXCITATION_KINDS = ('random_hold', 'prbs')
REFERENCE_KINDS = ('setpoint_sequence', 'setpoint', 'steps', 'sine')
# Upper bound of the encoder history H the node accepts: the paper's H is ~10, and the history
# buffer (2 x MAX_HISTORY samples) is allocated at start.
MAX_HISTORY = 1000


@dataclass
class ReferenceParams:
    """The reference_* parameters; :meth:`resolve` turns them into make_reference arguments."""

    kind: str = param('setpoint_sequence', 'reference kind', choices=REFERENCE_KINDS,
                      renamed={'paper': 'setpoint_sequence'}, live=True)
    outputs: Tuple[int, ...] = param((0,), 'indices of the outputs that follow the reference',
                                     ge=0, live=True)
    values: Tuple[float, ...] = param((), "setpoint_sequence: set-points (default the paper's "
                                          f'{list(SetpointSequenceConfig.setpoints)}); setpoint: '
                                          'one value (default 0); steps: the value from each '
                                          'time on', item=float, live=True)
    per_output: bool = param(False, 'setpoint_sequence: values hold one value per output of '
                                    'reference_outputs for each set-point, row after row',
                             live=True)
    times: Tuple[float, ...] = param((), 'steps: increasing times, s since the plant reset',
                                     item=float, live=True)
    initial: float = param(0.0, 'steps: value before the first time', live=True)
    segment: float = param(SetpointSequenceConfig.segment, 'setpoint_sequence: seconds per '
                                                           'set-point', gt=0, live=True)
    start: float = param(SetpointSequenceConfig.start, "setpoint_sequence: start of the first "
                                                       "set-point's segment, s (that set-point "
                                                       'also holds before it)', live=True)
    amplitude: float = param(0.5, 'sine: amplitude', live=True)
    period: float = param(10.0, 'sine: period, s', gt=0, live=True)
    offset: float = param(0.0, 'sine: offset', live=True)
    phase: float = param(0.0, 'sine: phase, rad', live=True)

    def resolve(self, n_y: int) -> Dict[str, Any]:
        """The arguments of ``make_reference(kind, ...)`` for a plant with n_y outputs."""
        params: Dict[str, Any] = {'n_y': n_y, 'outputs': self.outputs}
        if self.per_output and self.kind != 'setpoint_sequence':
            raise ValueError(f'reference_per_output applies to setpoint_sequence, not '
                             f'{self.kind}')
        if self.kind == 'setpoint_sequence':
            setpoints = self.values or SetpointSequenceConfig.setpoints
            if self.per_output:
                width = len(self.outputs)
                if not self.values or len(self.values) % width:
                    raise ValueError(f'reference_per_output: reference_values must hold '
                                     f'{width} values (one per reference output) per '
                                     f'set-point, got {len(self.values)}')
                setpoints = [tuple(self.values[i:i + width])
                             for i in range(0, len(self.values), width)]
            params.update(setpoints=setpoints, segment=self.segment, start=self.start)
        elif self.kind == 'setpoint':
            if len(self.values) > 1:
                raise ValueError(f'reference setpoint takes one value in reference_values, '
                                 f'got {list(self.values)}')
            params['value'] = self.values[0] if self.values else 0.0
        elif self.kind == 'steps':
            if not self.values or len(self.values) != len(self.times):
                raise ValueError('reference steps needs reference_times and reference_values '
                                 f'of the same non-zero length, got {list(self.times)} and '
                                 f'{list(self.values)}')
            params.update(steps=tuple(zip(self.times, self.values)), initial=self.initial)
        else:
            params.update(amplitude=self.amplitude, period=self.period, offset=self.offset,
                          phase=self.phase)
        try:
            make_reference(self.kind, **params)
        except ValueError as err:
            raise ValueError(f'reference {self.kind}: {err}') from None
        return params


@dataclass
class ExcitationParams:
    """The excitation_* parameters of the input before a model."""

    kind: str = param('random_hold', 'excitation signal: random_hold is uniform levels, prbs '
                                     'a binary sequence', choices=EXCITATION_KINDS)
    amplitude: float = amplitude_param()
    center: Tuple[float, ...] = center_param()
    hold_s: float = param(0.5, 'excitation hold time, s', gt=0)
    seed: int = param(0, 'excitation seed', ge=0)

    def within(self, u_min: Sequence[float], u_max: Sequence[float]) -> ExcitationConfig:
        """The excitation signal's settings inside the input bounds (ValueError: a band that
        leaves them)."""
        config = ExcitationConfig(kind=self.kind, u_min=tuple(u_min), u_max=tuple(u_max),
                                  hold_s=self.hold_s, amplitude=self.amplitude,
                                  center=tuple(self.center))
        config.validate()
        return config


@dataclass
class ControllerConfig:
    """Everything the controller node is configured with.

    Attributes:
        rate_hz: tick rate on the node clock, Hz.
        mpc: latent MPC settings (horizon, weights, bounds, OSQP); also the NMPC's horizon,
            weights and bounds.
        n_y: plant outputs (= len(mpc.q)).
        n_u: plant inputs (= the length of mpc's bounds and r; one value stands for every
            input, so 1 when all are single values).
        planner: a name of :data:`~metampc_controller.planner_registry.REGISTRY`.
        nmpc_tail: the NMPC's tail (:class:`~metampc_controller.nmpc.NmpcConfig`), samples.
        nmpc_solver: the NMPC's solver (:data:`~metampc_controller.nmpc.SOLVERS`).
        reference_kind, reference_params: arguments of references.make_reference.
        pre_model_input: 'zero' or 'excitation'.
        excitation: the pre-model excitation (kind, bounds = [u_min, u_max] within the
            amplitude, hold_s).
        excitation_seed: its seed.
        history: required H of the weights, 0 for any up to MAX_HISTORY.
        active: publish inputs from the start.
        trigger: when to ask the learner for adaptation in the loop.
        gate: when a new model may fly (which are checked, trial, probation).
        model_check: how the check a new model must pass scores it.
        hold: whether u and mpc_status wait for a full reader that keeps all.
        rls: a feature NARX's head adapted at every tick (off by default).
    """

    rate_hz: float = param(10.0, 'tick rate on the node clock, Hz (sim time under a lockstep '
                                 'plant: set it to 1/dt)', gt=0)
    mpc: MpcConfig = field(default_factory=MpcConfig)
    n_y: int = 2
    n_u: int = 1
    planner: str = param('latent_mpc', 'latent_mpc is eq. mpc on the NSSM, nmpc the true-model '
                                       'yardstick (theta from every y)', choices=PLANNERS)
    nmpc_tail: int = param(0, 'planner nmpc: samples predicted past the horizon with the last '
                              'input held, scored against the last reference (its terminal '
                              'cost; 0: none)', ge=0, le=1000, live=True)
    nmpc_solver: str = param('ipopt', 'planner nmpc: ipopt (multiple shooting on CasADi, exact '
                                      'derivatives) or lbfgsb (single shooting, finite '
                                      'differences: the yardstick until 2026-12-07)',
                             choices=NMPC_SOLVERS)
    reference_kind: str = 'setpoint_sequence'
    reference_params: Dict[str, Any] = field(default_factory=dict)
    pre_model_input: str = param('zero', 'input before a model (excitation: seeded, within the '
                                         'bounds)', choices=PRE_MODEL_INPUTS)
    excitation: ExcitationConfig = field(default_factory=ExcitationConfig)
    excitation_seed: int = 0
    history: int = param(0, f'required encoder history H of the weights (0: any H up to '
                            f'{MAX_HISTORY})', ge=0, le=MAX_HISTORY)
    active: bool = param(True, 'publish inputs from the start (service set_active toggles)')
    trigger: TriggerConfig = field(default_factory=TriggerConfig)
    gate: GateConfig = field(default_factory=GateConfig)
    model_check: ModelCheckConfig = field(default_factory=ModelCheckConfig)
    hold: HoldConfig = field(default_factory=HoldConfig)
    rls: RlsConfig = field(default_factory=RlsConfig)


MPC = Section(MpcConfig)
REFERENCE = Section(ReferenceParams, 'reference_', rename={'kind': 'reference'})
EXCITATION = Section(ExcitationParams, 'excitation_')
TRIGGER = Section(TriggerConfig)
GATE = Section(GateConfig)
CHECK = Section(ModelCheckConfig)
HOLD = Section(HoldConfig)
RLS = Section(RlsConfig)
NODE = Section(ControllerConfig)
SECTIONS = (NODE, MPC, REFERENCE, EXCITATION, TRIGGER, GATE, CHECK, HOLD, RLS)
PARAMETERS: Dict[str, ParamSpec] = table(SECTIONS)


def parse_params(values: Mapping[str, Value]) -> ControllerConfig:
    """Turn raw parameter values (as ROS gives them) into a checked :class:`ControllerConfig`.

    Raises:
        ParameterError: naming the first parameter that is of the wrong type or out of range.
    """
    try:
        mpc = build(MPC, values)
    except ValueError as err:     # MpcConfig checks in __post_init__, before build() can
        raise ParameterError(str(err)) from None
    if not mpc.q:
        raise ParameterError('q needs one weight per plant output, got []')
    node = build(NODE, values, mpc=mpc, n_y=len(mpc.q), n_u=mpc.n_u)
    reference = build(REFERENCE, values)
    try:
        reference_params = reference.resolve(len(mpc.q))
    except ValueError as err:
        raise ParameterError(str(err)) from None
    excitation = build(EXCITATION, values)
    node.reference_kind, node.reference_params = reference.kind, reference_params
    try:
        node.excitation = excitation.within(*mpc.bounds(node.n_u))
    except ValueError as err:
        raise ParameterError(str(err)) from None
    node.excitation_seed = excitation.seed
    node.trigger = build(TRIGGER, values)
    node.gate = build(GATE, values)
    node.model_check = build(CHECK, values)
    for name in ('model_check_trial', 'model_check_probation'):
        samples = getattr(node.gate, name)
        if 0 < samples < mpc.horizon:
            raise ParameterError(f'{name} must be 0 or at least horizon ({mpc.horizon}) '
                                 f'samples, so that its check scores at least one prediction; '
                                 f'got {samples}')
    node.hold = build(HOLD, values)
    node.rls = build(RLS, values)
    return node


__all__ = ['PLANNERS', 'PRE_MODEL_INPUTS', 'EXCITATION_KINDS', 'REFERENCE_KINDS', 'MAX_HISTORY',
           'ReferenceParams', 'ExcitationParams', 'ControllerConfig', 'SECTIONS', 'PARAMETERS',
           'parse_params', 'ParameterError']
