"""Configuration of an experiment (``scripts/run_experiment.py --config FILE``), without rclpy.

A YAML file holds a mapping with the keys of :class:`ExperimentConfig`; the missing ones keep
their defaults and an unknown key is an error, so a typo never passes silently. The node
sections (``plant``, ``learner``, ``controller``, ``recorder``) are ROS parameters handed to
the nodes as they are: the nodes check them and the orchestrator reports a node's one-line
error if one is refused. The keys shared by several nodes (``dt``, ``u_min``, ``u_max``) are
set once at the top and copied into every node that takes them; the per-seed values (seeds,
target theta) are set by :meth:`ExperimentConfig.node_parameters`.

Requests: ``meta_train.<method>`` are the fields of a ``MetaTrain`` request for each meta
method, ``adapt.<method>`` those of an ``Adapt`` request for each method that adapts (a
field left out keeps the learner's parameter).

Protocols (``protocol``), applied to those requests by :meth:`ExperimentConfig.meta_request`
and :meth:`ExperimentConfig.adapt_request`:

- ``tuned`` (the default, ``make run``): the requests as written; the tuned set-up adapts
  every method by plain steps (gamma = 0) and meta-trains on the simulated source set alone.
- ``paper``: the paper as written: Algorithm 1 collects closed-loop source data during
  meta-training (eq. ub, ``online_collection``), iMAML adapts by eq. (infer) with the gamma it
  was meta-trained with, first-order MAML and supervised training by plain steps (eq. inner).
"""
from dataclasses import asdict, dataclass, field, fields
import math
from typing import Any, Dict, List, Optional

import numpy as np
import yaml

from metampc_controller import controller_params
from metampc_learner import learner_params
from metampc_msgs.srv import Adapt, MetaTrain

PROTOCOLS = ('tuned', 'paper')
META_METHODS = ('imaml', 'maml', 'maml_unrolled')
ADAPT_METHODS = (*META_METHODS, 'supervised', 'oracle')
METHODS = (*ADAPT_METHODS, 'nmpc')
SHARED = ('dt', 'u_min', 'u_max')
_TAKES_SHARED = {'plant': SHARED, 'learner': SHARED, 'controller': ('u_min', 'u_max')}
# The request fields a config may set: the services' own (method and seed are the run's).
_META_FIELDS = set(MetaTrain.Request.get_fields_and_field_types()) - {'method', 'seed'}
_ADAPT_FIELDS = set(Adapt.Request.get_fields_and_field_types()) - {'method'}


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
class ExperimentConfig:
    """Everything an experiment needs; defaults are the paper's set-up.

    Attributes:
        methods: what to compare, in order (:data:`METHODS`).
        seeds: number of seeds; seed ``first_seed + i`` seeds run i (its own bring-up).
        theta: target damping theta*; None draws it per seed from N(theta_mean, theta_std^2).
        target_samples: samples of the target plant collected under the controller's
            exploration input before any model exists (D_target of eq. infer).
        collect_x0 / track_x0: initial plant state of the collection / of every tracking run.
        track_duration: tracking run length, s of plant time (the paper reference: 30 s).
        tracked_outputs: output indices with a reference (metrics cover these).
        dt, u_min, u_max: sample time (s) and input bounds, shared by the nodes.
        plant, learner, controller, recorder: ROS parameters of each node.
        meta_train / adapt: request fields per method (see the module docstring).
        protocol: 'tuned' or 'paper' (see the module docstring).
        timeouts: see :class:`Timeouts`.
    """

    methods: List[str] = field(
        default_factory=lambda: ['imaml', 'maml', 'supervised', 'oracle', 'nmpc'])
    seeds: int = 1
    first_seed: int = 0
    theta: Optional[float] = None
    theta_mean: float = 0.0
    theta_std: float = 1.0
    target_samples: int = 300
    collect_x0: List[float] = field(default_factory=lambda: [0.5, 0.0])
    track_x0: List[float] = field(default_factory=lambda: [0.0, 0.0])
    track_duration: float = 30.0
    tracked_outputs: List[int] = field(default_factory=lambda: [0])
    dt: float = 0.1
    u_min: float = -1.0
    u_max: float = 1.0
    plant: Dict[str, Any] = field(default_factory=dict)
    learner: Dict[str, Any] = field(default_factory=dict)
    controller: Dict[str, Any] = field(default_factory=dict)
    recorder: Dict[str, Any] = field(default_factory=dict)
    meta_train: Dict[str, Dict[str, Any]] = field(default_factory=dict)
    adapt: Dict[str, Dict[str, Any]] = field(default_factory=dict)
    protocol: str = 'tuned'
    timeouts: Timeouts = field(default_factory=Timeouts)

    # --- derived ---------------------------------------------------------------------------

    def meta_methods(self) -> List[str]:
        """Meta methods to meta-train: those compared, in order."""
        return [m for m in self.methods if m in META_METHODS]

    def seed_list(self) -> List[int]:
        return [self.first_seed + i for i in range(self.seeds)]

    def target_theta(self, seed: int) -> float:
        """theta* of the run with `seed`: the given theta, else a seeded draw."""
        if self.theta is not None:
            return float(self.theta)
        rng = np.random.default_rng([seed, 0x7e7a])    # not the stream of any node
        return float(rng.normal(self.theta_mean, self.theta_std))

    def track_steps(self) -> int:
        """Samples of one tracking run."""
        return int(round(self.track_duration / self.dt))

    def node_parameters(self, node: str, seed: int) -> Dict[str, Any]:
        """ROS parameters of `node` ('plant', 'learner', 'controller') for the run `seed`."""
        params = {key: getattr(self, key) for key in _TAKES_SHARED[node]}
        params.update(getattr(self, node))
        if node == 'plant':
            params.update(mode='lockstep', theta=self.target_theta(seed), seed=seed,
                          x0=list(self.collect_x0), input_timeout=0.0)
        elif node == 'learner':
            params.update(seed=seed, source_seed=seed, target_buffer_size=self.target_samples,
                          theta_mean=self.theta_mean, theta_std=self.theta_std)
        else:
            params.update(excitation_seed=seed, active=False, use_sim_time=True,
                          rate_hz=1.0 / self.dt)
        return params

    def meta_request(self, method: str) -> Dict[str, Any]:
        """The MetaTrain request fields of `method` under the protocol."""
        fields = dict(self.meta_train.get(method) or {})
        if self.protocol == 'paper':
            fields['online_collection'] = True
        return fields

    def adapt_request(self, method: str) -> Dict[str, Any]:
        """The Adapt request fields of `method` under the protocol."""
        fields = dict(self.adapt.get(method) or {})
        if self.protocol == 'paper' and method in ('imaml', 'maml', 'supervised'):
            fields['gamma'] = (float(self.meta_train['imaml']['gamma']) if method == 'imaml'
                               else 0.0)
        return fields

    def to_dict(self) -> Dict[str, Any]:
        return asdict(self)

    # --- checks ----------------------------------------------------------------------------

    def validate(self) -> 'ExperimentConfig':
        """Raise ConfigError on a value the orchestrator cannot run with; return self."""
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown or not self.methods or len(set(self.methods)) != len(self.methods):
            raise ConfigError(f'methods must be distinct names out of {", ".join(METHODS)}; '
                              f'got {self.methods}')
        if self.seeds < 1 or self.first_seed < 0:
            raise ConfigError('seeds must be >= 1 and first_seed >= 0')
        if self.theta is not None and not math.isfinite(self.theta):
            raise ConfigError(f'theta must be finite, got {self.theta}')
        if not (self.dt > 0 and self.track_duration >= self.dt and self.target_samples >= 2):
            raise ConfigError('need dt > 0, track_duration >= dt and target_samples >= 2')
        if not self.u_min <= self.u_max:
            raise ConfigError(f'u_min {self.u_min} > u_max {self.u_max}')
        for name in ('collect_x0', 'track_x0'):
            if len(getattr(self, name)) != 2:
                raise ConfigError(f'{name} must be [x1, x2]')
        for node, shared in _TAKES_SHARED.items():
            clash = sorted(set(shared) & set(getattr(self, node)))
            if clash:
                raise ConfigError(f'{node}: set {", ".join(clash)} at the top level (shared '
                                  'by the nodes), not in the node section')
        if self.protocol not in PROTOCOLS:
            raise ConfigError(f'protocol must be one of {", ".join(PROTOCOLS)}, got '
                              f'{self.protocol!r}')
        if (self.protocol == 'paper' and 'imaml' in self.methods
                and 'gamma' not in (self.meta_train.get('imaml') or {})):
            raise ConfigError('protocol paper: iMAML adapts with its meta-training gamma; set '
                              'meta_train.imaml.gamma')
        _check_requests('meta_train', self.meta_train, META_METHODS, _META_FIELDS)
        _check_requests('adapt', self.adapt, ADAPT_METHODS, _ADAPT_FIELDS)
        for node, params in _NODE_PARAMS.items():
            _check_node(node, self.node_parameters(node, self.first_seed), *params)
        return self


# The learner's and the controller's declared parameters and parse functions: their sections
# are checked before anything starts. (The plant package is physics and its node, not imported
# here: a bad plant key is refused by the plant node itself at bring-up, one line, exit 2.)
_NODE_PARAMS = {'learner': (learner_params.PARAMETERS, learner_params.parse_params),
                'controller': (controller_params.PARAMETERS, controller_params.parse_params)}
_ROS_PARAMS = ('use_sim_time',)


def _check_node(node: str, params: Dict[str, Any], table, parse) -> None:
    """The node section's keys are declared parameters and its values parse."""
    unknown = sorted(set(params) - set(table) - set(_ROS_PARAMS))
    if unknown:
        raise ConfigError(f'{node}: unknown parameter(s) {", ".join(unknown)} (docs/{node}.md '
                          'lists them)')
    values = {name: spec.default for name, spec in table.items()}
    values.update({k: v for k, v in params.items() if k in table})
    try:
        parse(values)
    except ValueError as err:
        raise ConfigError(f'{node}: {err}') from None


def _check_requests(section: str, requests: Dict[str, Dict[str, Any]], methods, allowed) -> None:
    for method, request in requests.items():
        if method not in methods:
            raise ConfigError(f'{section}: unknown method {method!r} (one of '
                              f'{", ".join(methods)})')
        extra = sorted(set(request or {}) - allowed)
        if extra:
            raise ConfigError(f'{section}.{method}: unknown field(s) {", ".join(extra)} '
                              f'(allowed: {", ".join(sorted(allowed))})')


def from_mapping(data: Dict[str, Any]) -> ExperimentConfig:
    """An ExperimentConfig from a mapping (e.g. parsed YAML); ConfigError on unknown keys."""
    names = {f.name for f in fields(ExperimentConfig)}
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
