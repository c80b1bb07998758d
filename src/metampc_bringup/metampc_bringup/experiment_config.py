"""Configuration of an experiment (``scripts/run_experiment.py --config FILE``), without rclpy.

A YAML mapping with the keys of :class:`ExperimentConfig` (a missing key keeps its default, an
unknown key is an error). The node sections (``plant``, ``learner``, ``controller``,
``recorder``) are ROS parameters handed to the nodes as they are (the nodes check them);
``family``, ``dt``, ``u_min``, ``u_max`` are set once, copied into every node taking them.
``meta_train.<method>`` and ``adapt.<method>`` are the request fields per method, applied by
the ``protocol``: 'tuned' (as written, plain adaptation steps) or 'paper_settings' (Algorithm
1 with online collection, eq. (ub); iMAML adapts by eq. (infer) with its meta-training gamma).
A method 'narx_<m>' is the learner's <m> of the feature NARX (:func:`learner_method`).
Renamed names work for one release, with a warning (:mod:`metampc_common.renames`); a bad
file is a :class:`ConfigError`. Keys, protocols and renames: docs/experiments.md.
"""
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np
import yaml

from metampc_common.params import ParameterError, upgraded
from metampc_common.renames import renamed_value
from metampc_controller import controller_params
from metampc_learner import learner_params
from metampc_learner.learner_params import ADAPT_METHODS
from metampc_learner.meta_train import META_METHODS
from metampc_learner.target_fit import NARX_ADAPT_METHODS
from metampc_msgs.srv import Adapt, MetaTrain
from metampc_plant.family import PlantFamily
from metampc_plant.registry import DEFAULT, get_family
from metampc_plant.simulator import PlantConfig
from metampc_plant.steady_state import steady_output
from metampc_plant.theta_schedule import ThetaSchedule

PROTOCOLS = ('tuned', 'paper_settings')
SCENARIOS = ('adapt_once', 'drift')
# Values renamed in this release, {key: {old: new}}: the old ones work until the next.
_RENAMED = {'protocol': {'paper': 'paper_settings'}, 'scenario': {'paper': 'adapt_once'}}
DRIFT_MODES = ('none', 'periodic', 'triggered')
# The feature NARX's methods beside the NSSM's in one run (the learner's model_class nssm, each
# request naming the class): 'narx_imaml' is the learner's 'imaml' of model_class feature_narx.
NARX_PREFIX = 'narx_'
PREFIXED_NARX_METHODS = tuple(NARX_PREFIX + m for m in NARX_ADAPT_METHODS)
METHODS = (*ADAPT_METHODS, *PREFIXED_NARX_METHODS, 'nmpc')       # what an experiment compares
# ... with learner.model_class feature_narx (no supervised or unrolled MAML of that class)
NARX_EXPERIMENT_METHODS = (*NARX_ADAPT_METHODS, 'nmpc')
SHARED = ('family', 'dt', 'u_min', 'u_max')
_TAKES_SHARED = {'plant': SHARED, 'learner': SHARED, 'controller': ('u_min', 'u_max')}
# The request fields a config may set: the services' own (method and seed are the run's).
# (The model class is the method's: learner_method.)
_META_FIELDS = (set(MetaTrain.Request.get_fields_and_field_types())
                - {'method', 'seed', 'model_class'})
_ADAPT_FIELDS = set(Adapt.Request.get_fields_and_field_types()) - {'method', 'model_class'}


def learner_method(method: str) -> Tuple[str, str]:
    """The learner's (method, model_class) of an experiment's `method`: 'narx_imaml' ->
    ('imaml', 'feature_narx'); any other its own name and '' (the learner's model_class)."""
    if method in PREFIXED_NARX_METHODS:
        return method[len(NARX_PREFIX):], 'feature_narx'
    return method, ''


def experiment_method(method: str, model_class: str, learner_class: str) -> str:
    """The experiment's name of a model the learner published as `method` of `model_class`,
    on a learner whose model_class is `learner_class` (:func:`learner_method` inverted)."""
    return (NARX_PREFIX + method if model_class == 'feature_narx' != learner_class
            else method)


class ConfigError(ValueError):
    """An experiment configuration that cannot run; the message says which key and why."""


@dataclass
class Timeouts:
    """Wall-time limits, s: a phase that overruns ends the run with an error naming it."""

    startup: float = 60.0       # every node up, services and latched topics ready
    meta_train: float = 3600.0  # one meta_train call
    adapt: float = 900.0        # one adapt call (the oracle simulates and trains)
    phase: float = 600.0        # collecting target samples, or one tracking run


@dataclass
class DriftConfig:
    """The ``drift`` scenario (docs/adaptation.md): after the meta-training and one
    adaptation, each method tracks while theta* changes, once per adaptation mode.

    Attributes:
        schedule: the plant's theta_schedule rows ``[t_start, t_end, delta...]`` (s of the
            tracking run's plant time) whose theta is ``theta* + delta`` (the target drawn per
            seed moves by the same amount in every seed).
        modes: the controller's adaptation modes to compare ('none': adapted once only).
        methods: the methods that track (meta methods and 'supervised', out of ``methods``).
        duration: length of each tracking run, s of plant time.
        constant_check: also one 'triggered' run per method with a constant theta: the
            adaptations it makes are spurious.
    """

    schedule: List[float] = field(default_factory=lambda: [30.0, 30.0, -1.0])
    modes: List[str] = field(default_factory=lambda: list(DRIFT_MODES))
    methods: List[str] = field(default_factory=lambda: ['imaml', 'maml', 'supervised'])
    duration: float = 60.0
    constant_check: bool = True

    def theta_schedule(self, theta: List[float]) -> List[float]:
        """The plant's schedule for target `theta` (the deltas added)."""
        n = len(theta)
        rows = [self.schedule[i:i + 2 + n] for i in range(0, len(self.schedule), 2 + n)]
        return [v for row in rows for v in (row[0], row[1],
                                            *(t + d for t, d in zip(theta, row[2:])))]

    def change_times(self, n_theta: int) -> List[float]:
        """The starts of the schedule's segments, s."""
        return [float(v) for v in self.schedule[0::2 + n_theta]]


@dataclass
class ExperimentConfig:
    """Everything an experiment needs; defaults are the paper's set-up.

    Attributes:
        methods: what to compare, in order (:data:`METHODS`).
        seeds: number of seeds; seed ``first_seed + i`` seeds run i (its own bring-up).
        family: the plant family (registered name, docs/families.md).
        theta: target theta* (a list of the family's n_theta values, or a number for a
            one-component family); None draws it per seed from the family's prior Theta.
        target_samples: samples of the target plant collected under the controller's
            exploration input before any model exists (D_target of eq. infer).
        collect_x0 / track_x0: initial plant state of the collection / of every tracking run
            (None: the family's x0).
        track_duration: tracking run length, s of plant time (the paper reference: 30 s).
        tracked_outputs: output indices with a reference (metrics cover these; None: the
            family's).
        reference_inputs: constant inputs, one row of n_u values per set-point: the
            set-points become the tracked outputs of the target's steady state there (per
            seed's theta*), so the target can hold every one (None: controller.reference_values
            as given).
        dt, u_min, u_max: sample time (s) and input bounds (a list, one per input, or one
            number for every input), shared by the nodes; None: the family's.
        plant, learner, controller, recorder: ROS parameters of each node.
        meta_train / adapt: request fields per method (see the module docstring).
        protocol: 'tuned' or 'paper_settings' (see the module docstring).
        scenario: 'adapt_once' (adapt once, track once per method) or 'drift' (theta* changes
            while each method tracks, with and without adaptation in the loop:
            :class:`DriftConfig`).
        drift: the drift scenario's settings (a mapping of :class:`DriftConfig`'s fields).
        timeouts: see :class:`Timeouts`.
    """

    methods: List[str] = field(
        default_factory=lambda: ['imaml', 'maml', 'supervised', 'oracle', 'nmpc'])
    seeds: int = 1
    first_seed: int = 0
    family: str = DEFAULT
    theta: Optional[Union[float, List[float]]] = None
    target_samples: int = 300
    collect_x0: Optional[List[float]] = None
    track_x0: Optional[List[float]] = None
    track_duration: float = 30.0
    tracked_outputs: Optional[List[int]] = None
    reference_inputs: Optional[List[List[float]]] = None
    dt: Optional[float] = None
    u_min: Optional[Union[float, List[float]]] = None
    u_max: Optional[Union[float, List[float]]] = None
    plant: Dict[str, Any] = field(default_factory=dict)
    learner: Dict[str, Any] = field(default_factory=dict)
    controller: Dict[str, Any] = field(default_factory=dict)
    recorder: Dict[str, Any] = field(default_factory=dict)
    meta_train: Dict[str, Dict[str, Any]] = field(default_factory=dict)
    adapt: Dict[str, Dict[str, Any]] = field(default_factory=dict)
    protocol: str = 'tuned'
    scenario: str = 'adapt_once'
    drift: Dict[str, Any] = field(default_factory=dict)
    timeouts: Timeouts = field(default_factory=Timeouts)

    # --- derived ---------------------------------------------------------------------------

    @property
    def plant_family(self) -> PlantFamily:
        """The family object (ConfigError if it is not installed)."""
        try:
            return get_family(self.family)
        except ValueError as err:
            raise ConfigError(f'family: {err}') from None

    def resolved(self) -> 'ExperimentConfig':
        """A copy with every null filled in from the family and the bounds as lists."""
        fam = self.plant_family

        def bounds(value, default):
            if value is None:
                return list(default)
            values = [float(v) for v in np.atleast_1d(value)]
            return values * fam.n_u if len(values) == 1 else values
        out = replace(
            self, dt=float(self.dt or fam.dt), u_min=bounds(self.u_min, fam.u_min),
            u_max=bounds(self.u_max, fam.u_max),
            collect_x0=list(self.collect_x0 if self.collect_x0 is not None else fam.x0),
            track_x0=list(self.track_x0 if self.track_x0 is not None else fam.x0),
            tracked_outputs=list(self.tracked_outputs if self.tracked_outputs is not None
                                 else fam.tracked))
        return out

    def meta_methods(self) -> List[str]:
        """Meta methods to meta-train: those compared, in order (experiment names)."""
        return [m for m in self.methods if learner_method(m)[0] in META_METHODS]

    def drift_config(self) -> DriftConfig:
        """The drift scenario's settings (ConfigError on an unknown key)."""
        names = {f.name for f in fields(DriftConfig)}
        unknown = sorted(set(self.drift) - names)
        if unknown:
            raise ConfigError(f'drift: unknown key(s) {", ".join(unknown)}; known: '
                              f'{", ".join(sorted(names))}')
        return DriftConfig(**self.drift)

    def seed_list(self) -> List[int]:
        return [self.first_seed + i for i in range(self.seeds)]

    def target_theta(self, seed: int) -> List[float]:
        """theta* of the run with `seed` (n_theta values): the given theta, else a seeded draw
        from the family's prior."""
        if self.theta is not None:
            return [float(v) for v in np.atleast_1d(self.theta)]
        rng = np.random.default_rng([seed, 0x7e7a])    # not the stream of any node
        return self.plant_family.sample_theta(rng, 1)[0].tolist()

    def reachable_setpoints(self, seed: int) -> List[float]:
        """The set-points of ``reference_inputs`` for run `seed`: the tracked outputs of
        theta*'s steady state at each row, row after row (ConfigError if one has none)."""
        cfg = self.resolved()
        theta = cfg.target_theta(seed)
        values = []
        for row in cfg.reference_inputs:
            try:
                y = steady_output(cfg.plant_family, theta, row)
            except ValueError as err:
                raise ConfigError(f'reference_inputs (seed {seed}): {err}') from None
            values += [float(y[j]) for j in cfg.tracked_outputs]
        return values

    def track_steps(self) -> int:
        """Samples of one tracking run."""
        return int(round(self.track_duration / self.dt))

    def node_parameters(self, node: str, seed: int) -> Dict[str, Any]:
        """ROS parameters of `node` ('plant', 'learner', 'controller') for the run `seed`."""
        cfg = self.resolved()
        params = {key: getattr(cfg, key) for key in _TAKES_SHARED[node]}
        if node == 'controller':
            fam = cfg.plant_family
            params['q'] = [1.0 if j in cfg.tracked_outputs else 0.0 for j in range(fam.n_y)]
        params.update(getattr(cfg, node))
        if node == 'controller' and cfg.reference_inputs:
            params.update(reference='setpoint_sequence', reference_per_output=True,
                          reference_outputs=list(cfg.tracked_outputs),
                          reference_values=cfg.reachable_setpoints(seed))
        if node == 'plant':
            params.update(mode='lockstep', theta=cfg.target_theta(seed), seed=seed,
                          x0=list(cfg.collect_x0), input_timeout=0.0)
        elif node == 'learner':
            params.update(seed=seed, source_seed=seed, target_buffer_size=cfg.target_samples)
            if cfg.scenario == 'drift':
                params['loop_adaptation'] = True
        else:
            params.update(excitation_seed=seed, active=False, use_sim_time=True,
                          rate_hz=1.0 / cfg.dt)
        return params

    def meta_request(self, method: str) -> Dict[str, Any]:
        """The MetaTrain request fields of `method` under the protocol, typed as the request's
        fields (a YAML ``1`` for a double is 1.0)."""
        fields = dict(self.meta_train.get(method) or {})
        if self.protocol == 'paper_settings':
            fields['online_collection'] = True
        return _typed(f'meta_train.{method}', fields, MetaTrain.Request)

    def adapt_request(self, method: str) -> Dict[str, Any]:
        """The Adapt request fields of `method` under the protocol, typed as the request's."""
        fields = dict(self.adapt.get(method) or {})
        if self.protocol == 'paper_settings' and method in ('imaml', 'maml', 'supervised'):
            fields['gamma'] = (float(self.meta_train['imaml']['gamma']) if method == 'imaml'
                               else 0.0)
        return _typed(f'adapt.{method}', fields, Adapt.Request)

    def node_config(self, node: str, seed: int) -> Any:
        """The typed configuration that the learner or controller node parses from its
        section (e.g. ``node_config('learner', s).torch_threads``); ConfigError if invalid."""
        return _check_node(node, self.node_parameters(node, seed), *_NODE_PARAMS[node])

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)

    # --- checks ----------------------------------------------------------------------------

    def validate(self) -> 'ExperimentConfig':
        """Raise ConfigError on a value the orchestrator cannot run with; return the config
        with the family's defaults filled in (:meth:`resolved`)."""
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown or not self.methods or len(set(self.methods)) != len(self.methods):
            raise ConfigError(f'methods must be distinct names out of {", ".join(METHODS)}; '
                              f'got {self.methods}')
        if self.seeds < 1 or self.first_seed < 0:
            raise ConfigError('seeds must be >= 1 and first_seed >= 0')
        fam = self.plant_family
        cfg = self.resolved()
        if not (cfg.dt > 0 and cfg.track_duration >= cfg.dt and cfg.target_samples >= 2):
            raise ConfigError('need dt > 0, track_duration >= dt and target_samples >= 2')
        # theta*, the bounds and the initial states as the plant node will check them.
        try:
            plant = PlantConfig(family=fam.name, dt=cfg.dt, u_min=tuple(cfg.u_min),
                                u_max=tuple(cfg.u_max),
                                theta=tuple(cfg.target_theta(cfg.first_seed))).resolved()
        except (ValueError, TypeError) as err:
            raise ConfigError(str(err)) from None
        for name in ('collect_x0', 'track_x0'):
            try:
                replace(plant, x0=tuple(getattr(cfg, name))).resolved()
            except ValueError as err:
                raise ConfigError(f'{name}: {err}') from None
        if any(j not in range(fam.n_y) for j in cfg.tracked_outputs) or not cfg.tracked_outputs:
            raise ConfigError(f'tracked_outputs must be indices in [0, {fam.n_y}) (family '
                              f'{fam.name}), got {self.tracked_outputs}')
        for node, shared in _TAKES_SHARED.items():
            clash = sorted(set(shared) & set(getattr(self, node)))
            if clash:
                raise ConfigError(f'{node}: set {", ".join(clash)} at the top level (shared '
                                  'by the nodes), not in the node section')
        if self.protocol not in PROTOCOLS:
            raise ConfigError(f'protocol must be one of {", ".join(PROTOCOLS)}, got '
                              f'{self.protocol!r}')
        if (self.protocol == 'paper_settings' and 'imaml' in self.methods
                and 'gamma' not in (self.meta_train.get('imaml') or {})):
            raise ConfigError('protocol paper_settings: iMAML adapts with its meta-training '
                              'gamma; set meta_train.imaml.gamma')
        narx = [m for m in self.meta_methods() if m in PREFIXED_NARX_METHODS]
        if self.protocol == 'paper_settings' and narx:
            raise ConfigError(f'protocol paper_settings collects online, the NSSM\'s only: '
                              f'not for {", ".join(narx)}')
        if self.scenario not in SCENARIOS:
            raise ConfigError(f'scenario must be one of {", ".join(SCENARIOS)}, got '
                              f'{self.scenario!r}')
        if self.scenario == 'drift':
            _check_drift(self, fam, cfg)
        if self.reference_inputs is not None:
            _check_reference_inputs(self, fam)
        _check_requests('meta_train', self.meta_train,
                        [m for m in METHODS if learner_method(m)[0] in META_METHODS],
                        _META_FIELDS)
        _check_requests('adapt', self.adapt, (*ADAPT_METHODS, *PREFIXED_NARX_METHODS),
                        _ADAPT_FIELDS)
        for node in _NODE_PARAMS:
            self.node_config(node, self.first_seed)
        if self.node_config('learner', self.first_seed).model_class == 'feature_narx':
            unfit = [m for m in self.methods if m not in NARX_EXPERIMENT_METHODS]
            if unfit:
                raise ConfigError(f'methods {", ".join(unfit)}: not of learner.model_class '
                                  f'feature_narx (its methods: '
                                  f'{", ".join(NARX_EXPERIMENT_METHODS)})')
        return cfg


def _check_reference_inputs(config: ExperimentConfig, fam: PlantFamily) -> None:
    """reference_inputs: rows of n_u numbers, and the controller section leaves the reference
    to them (the set-points of every seed are computed at its bring-up)."""
    rows = config.reference_inputs
    if not rows or any(np.ndim(r) != 1 or len(r) != fam.n_u for r in rows):
        raise ConfigError(f'reference_inputs must be rows of {fam.n_u} input values (family '
                          f'{fam.name}), one per set-point; got {rows}')
    taken = sorted({'reference', 'reference_values', 'reference_outputs',
                    'reference_per_output'} & set(config.controller))
    if taken:
        raise ConfigError(f'reference_inputs sets the reference: leave {", ".join(taken)} out '
                          f'of the controller section')


def _check_drift(config: ExperimentConfig, fam: PlantFamily, cfg: ExperimentConfig) -> None:
    """The drift scenario's settings as the nodes will take them: its schedule on the first
    seed's theta* (every seed's is checked by the plant at its reset), modes, methods."""
    drift = config.drift_config()
    bad_modes = [m for m in drift.modes if m not in DRIFT_MODES]
    if bad_modes or not drift.modes:
        raise ConfigError(f'drift.modes must be out of {", ".join(DRIFT_MODES)}, got '
                          f'{drift.modes}')
    trackers = [m for m in drift.methods if m in (*META_METHODS, 'supervised')]
    missing = [m for m in drift.methods if m not in config.methods]
    if not drift.methods or trackers != drift.methods or missing:
        raise ConfigError(f'drift.methods must be meta methods or supervised, out of methods '
                          f'{config.methods}; got {drift.methods}')
    if 'nmpc' not in config.methods:
        raise ConfigError('scenario drift measures recovery against the true-model NMPC: add '
                          'nmpc to methods')
    if not drift.duration >= cfg.dt:
        raise ConfigError(f'drift.duration must be >= dt, got {drift.duration}')
    if 'adaptation' in config.controller:
        raise ConfigError('controller.adaptation is set per run by scenario drift '
                          '(drift.modes)')
    try:
        ThetaSchedule.parse(drift.theta_schedule(cfg.target_theta(cfg.first_seed)), fam,
                            cfg.target_theta(cfg.first_seed))
    except (ValueError, IndexError) as err:
        raise ConfigError(f'drift.schedule (theta* + delta of seed {cfg.first_seed}): '
                          f'{err}') from None


# The learner's and the controller's declared parameters and parse functions: their sections
# are checked before anything starts. (The plant package is physics and its node, not imported
# here: a bad plant key is refused by the plant node itself at bring-up, one line, exit 2.)
_NODE_PARAMS = {'learner': (learner_params.PARAMETERS, learner_params.parse_params),
                'controller': (controller_params.PARAMETERS, controller_params.parse_params)}
_ROS_PARAMS = ('use_sim_time',)


def _check_node(node: str, params: Dict[str, Any], table, parse) -> Any:
    """The node section's keys are declared parameters and its values parse; the node's
    typed configuration."""
    unknown = sorted(set(params) - set(table) - set(_ROS_PARAMS))
    if unknown:
        raise ConfigError(f'{node}: unknown parameter(s) {", ".join(unknown)} (docs/{node}.md '
                          'lists them)')
    values = {name: spec.default for name, spec in table.items()}
    values.update({k: v for k, v in params.items() if k in table})
    try:
        return parse(values)
    except ValueError as err:
        raise ConfigError(f'{node}: {err}') from None


_FLOATS, _INTS = ('double', 'float'), ('int32', 'uint32', 'int64', 'uint64')


def _typed(where: str, fields: Dict[str, Any], request_type) -> Dict[str, Any]:
    """`fields` converted to the request's field types: an integer where a double is wanted
    is that number (the generated message code aborts the process on an int there), a whole
    float where an integer is wanted is that integer; ConfigError for anything else."""
    types = request_type.get_fields_and_field_types()
    out = {}
    for name, value in fields.items():
        kind = types.get(name)
        try:
            if kind in _FLOATS and not isinstance(value, bool):
                value = float(value)
            elif kind in _INTS and not isinstance(value, bool):
                if float(value) != int(value):
                    raise ValueError('not a whole number')
                value = int(value)
            elif kind == 'boolean' and not isinstance(value, bool):
                raise ValueError('not true or false')
        except (TypeError, ValueError) as err:
            raise ConfigError(f'{where}.{name}: {value!r} is not a {kind} ({err})') from None
        out[name] = value
    return out


def _check_requests(section: str, requests: Dict[str, Dict[str, Any]], methods, allowed) -> None:
    for method, request in requests.items():
        if method not in methods:
            raise ConfigError(f'{section}: unknown method {method!r} (one of '
                              f'{", ".join(methods)})')
        extra = sorted(set(request or {}) - allowed)
        if extra:
            raise ConfigError(f'{section}.{method}: unknown field(s) {", ".join(extra)} '
                              f'(allowed: {", ".join(sorted(allowed))})')
        _typed(f'{section}.{method}', request or {},
               MetaTrain.Request if section == 'meta_train' else Adapt.Request)


# Keys of earlier versions, with the only value the current code reproduces: the van der Pol
# prior N(0, 1) is now the family's (so the run configs of older recordings still load).
_RETIRED = {'theta_mean': 0.0, 'theta_std': 1.0}


def _current(data: Dict[str, Any]) -> Dict[str, Any]:
    """`data` under today's names: a renamed value of a top-level key, a node parameter under
    its former name or with a renamed choice replaced, with one warning line each; ConfigError
    if a node parameter is given under both names."""
    out = dict(data)
    for key, renames in _RENAMED.items():
        if key in out:
            out[key] = renamed_value(out[key], renames, f'config: {key}')
    for node, (table, _) in _NODE_PARAMS.items():
        if isinstance(out.get(node), dict):
            try:
                out[node] = upgraded(out[node], table, f'config: {node}.')
            except ParameterError as err:
                raise ConfigError(str(err)) from None
    return out


def from_mapping(data: Dict[str, Any]) -> ExperimentConfig:
    """An ExperimentConfig from a mapping (e.g. parsed YAML); ConfigError on unknown keys.
    Names renamed in this release are taken with a warning (the module docstring)."""
    names = {f.name for f in fields(ExperimentConfig)}
    data = _current(data)
    for key, value in _RETIRED.items():
        if key in data and data.pop(key) != value:
            raise ConfigError(f'{key} is retired: theta* is drawn from the family\'s prior '
                              '(docs/families.md: a variant of a family with another prior)')
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f'unknown key(s) {", ".join(unknown)}; '
                          f'known: {", ".join(sorted(names))}')
    data = dict(data)
    timeouts = data.pop('timeouts', None) or {}
    bad = sorted(set(timeouts) - {f.name for f in fields(Timeouts)})
    if bad:
        raise ConfigError(f'timeouts: unknown key(s) {", ".join(bad)}')
    try:
        config = ExperimentConfig(**data, timeouts=Timeouts(**timeouts))
    except TypeError as err:
        raise ConfigError(str(err)) from None
    return config


def learner_config(experiment: ExperimentConfig, seed: int) -> learner_params.LearnerNodeConfig:
    """The learner node's configuration in the experiment's run `seed` (checked)."""
    values = {name: spec.default for name, spec in learner_params.PARAMETERS.items()}
    values.update(experiment.node_parameters('learner', seed))
    return learner_params.parse_params(values)


def load(path: Optional[str], overrides: Optional[Dict[str, Any]] = None) -> ExperimentConfig:
    """Read the YAML file `path` (None: defaults), apply `overrides`, validate."""
    data: Dict[str, Any] = {}
    if path:
        try:
            with open(path) as f:
                data = yaml.safe_load(f) or {}
        except OSError as err:
            raise ConfigError(f'cannot read config {path}: {err.strerror}') from None
        except yaml.YAMLError as err:
            raise ConfigError(f'config {path} is not valid YAML: {err}') from None
        if not isinstance(data, dict):
            raise ConfigError(f'config {path} must hold a mapping of keys to values')
    data.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return from_mapping(data).validate()
