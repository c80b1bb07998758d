"""Parameters of the `learner` node and its service requests.

Pure Python (no rclpy). Every parameter is declared once, on a field of a typed config
(:mod:`metampc_common.params`): the core configs (meta-training, NSSM, source set, excitation,
online collection, adaptation, oracle, adaptation in the loop, the feature NARX's sizes and
training) and :class:`LearnerNodeConfig`.
:data:`SECTIONS` names them with their prefixes; :data:`PARAMETERS`, :func:`parse_params` (raw
values -> checked config, or :class:`ParameterError` naming the first bad one) and the docs'
rows come from there. :func:`resolve_meta_request` and :func:`resolve_adapt_request` fill a
request's 0 / empty fields from the parameters, raising ``ValueError`` for a bad request;
:func:`fit_settings` is how ``target_fit.fit_target`` fits a resolved Adapt request.
Defaults and the tuned values: docs/learner.md, config/default.yaml.
"""
import math
from dataclasses import dataclass, field, replace
from typing import Dict, Mapping, Tuple

from metampc_common.params import (build, param, ParameterError, ParamSpec, Section, table,
                                   Value)
from metampc_common.excitation import ExcitationConfig
from metampc_model.narx_shape import NarxShape
from metampc_model.nssm_config import NssmConfig
from metampc_model.weights_codec import MODEL_CLASSES
from metampc_learner.adapt import AdaptConfig
from metampc_learner.data import SourceConfig
from metampc_learner.loop_adaptation import LoopConfig
from metampc_learner.meta_train import META_METHODS, MetaConfig
from metampc_learner.narx_learning import NARX_METHODS, NarxMetaConfig
from metampc_learner.online_collection import OnlineCollectionConfig
from metampc_learner.oracle import OracleConfig
from metampc_learner.target_fit import BASELINES, FitSettings

# The methods an Adapt request may name ('' too: the latest meta-model).
ADAPT_METHODS = (*META_METHODS, *BASELINES)


@dataclass
class LearnerNodeConfig:
    """Everything the learner node is configured with.

    Attributes:
        meta: meta-training defaults (Algorithm 1).
        nssm: architecture of new models.
        source: simulated source systems.
        online: closed-loop collection settings (eq. ub).
        adapt: adaptation defaults (eq. infer).
        oracle: oracle settings.
        loop: adaptation in the loop (at the controller's requests).
        narx: sizes of new feature NARX models (model_class feature_narx; n_u, n_y the
            family's).
        narx_meta: their meta-training (and adaptation) settings.
        (the others: the node's own parameters, described on their fields)
    """

    meta: MetaConfig = field(default_factory=MetaConfig)
    nssm: NssmConfig = field(default_factory=NssmConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    online: OnlineCollectionConfig = field(default_factory=OnlineCollectionConfig)
    adapt: AdaptConfig = field(default_factory=AdaptConfig)
    oracle: OracleConfig = field(default_factory=OracleConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    narx: NarxShape = field(default_factory=lambda: NarxShape(n_u=1, n_y=2))
    narx_meta: NarxMetaConfig = field(default_factory=NarxMetaConfig)
    model_class: str = param('nssm', "class of the models it trains: nssm (the paper's NSSM, "
                                     'eq. SSM) or feature_narx (a NARX linear in its head over '
                                     'lags and meta-learned features, docs/nonlinear.md)',
                             choices=MODEL_CLASSES)
    train_fraction: float = param(0.5, 'share (in time) of each source episode in D_tr',
                                  gt=0, lt=1)
    online_collection: bool = param(False, 'collect closed-loop source data during '
                                           'meta-training (a request can also turn it on)',
                                    live=True)
    online_max_samples: int = param(20000, 'cap of collected samples kept', ge=1)
    target_buffer_size: int = param(300, 'target samples kept after buffering (re)starts',
                                    ge=1)
    buffer_on_start: bool = param(True, 'buffer y from the start (false: only after '
                                        'set_buffering true)')
    arx_order: int = param(2, 'order p of the arx baseline: y_t from p past outputs and the '
                              'inputs u_t .. u_{t-p+1} (at most the history H; the '
                              'hidden layers need 2 (p (n_y + n_u) - n_u) units)', ge=1)
    gain_check: bool = param(False, 'refuse an adapted model whose steady-state gain on the '
                                    "family's tracked outputs disagrees in sign with the "
                                    'least-squares ARX of its samples, and publish that ARX in '
                                    'its place (gain_check.py)')
    heldout_fraction: float = param(0.2, 'last share of the buffered samples held out for the '
                                         'loss curve', gt=0, lt=1)
    meta_model_path: str = param('', "checkpoint to load at start and publish as stage meta "
                                     "('': none)")
    checkpoint_dir: str = param('', "directory for checkpoints of every trained model ('': "
                                    'none; created if missing)')
    torch_threads: int = param(1, 'torch intra-op threads (see docs/learner.md)', ge=1)
    progress_period: float = param(0.5, 'progress heartbeat while training, s', gt=0, le=1)

    def validate(self) -> None:
        """Rules across sections: every split holds at least one window of H + T samples; the
        feature NARX has no gain check, adaptation in the loop or online collection."""
        if self.model_class == 'feature_narx':
            for name, on in (('gain_check', self.gain_check),
                             ('loop_adaptation', self.loop.adaptation),
                             ('online_collection', self.online_collection)):
                if on:
                    raise ParameterError(f'{name}: the NSSM\'s only, not for model_class '
                                         'feature_narx')
        window = self.nssm.window
        d_tr = int(round(self.train_fraction * self.source.episode_samples))
        _check_split('episode_samples', d_tr, self.source.episode_samples - d_tr, window,
                     'D_tr / D_test parts (train_fraction)')
        held = int(round(self.heldout_fraction * self.target_buffer_size))
        _check_split('target_buffer_size', self.target_buffer_size - held, held, window,
                     'training / held-out parts (heldout_fraction)')
        if self.loop.window and not window <= self.loop.window <= self.target_buffer_size:
            raise ParameterError(f'loop_window: {self.loop.window} samples; it must hold a '
                                 f'window of H + T = {window} samples and fit the buffer of '
                                 f'target_buffer_size = {self.target_buffer_size}')


# The node's parameters: each config's fields, named prefix + field or as renamed.
META = Section(MetaConfig)
NSSM = Section(NssmConfig)
SOURCE = Section(SourceConfig, rename={'seed': 'source_seed'})
EXCITATION = Section(ExcitationConfig, rename={'kind': 'excitation',
                                               'amplitude': 'excitation_amplitude',
                                               'center': 'excitation_center'})
ONLINE = Section(OnlineCollectionConfig, 'online_',
                 rename={'episode_samples': 'online_samples'})
ADAPT = Section(AdaptConfig, 'adapt_')
ORACLE = Section(OracleConfig, 'oracle_', rename={'batch_windows': 'oracle_batch'})
LOOP = Section(LoopConfig, 'loop_')
NARX = Section(NarxShape, 'narx_')
NARX_META = Section(NarxMetaConfig, 'narx_')
NODE = Section(LearnerNodeConfig)
SECTIONS = (META, NSSM, SOURCE, EXCITATION, ONLINE, ADAPT, ORACLE, LOOP, NARX, NARX_META, NODE)
PARAMETERS: Dict[str, ParamSpec] = table(SECTIONS)


def _check_split(name: str, first: int, second: int, window: int, parts: str) -> None:
    """Both parts of a split must hold at least one window of H + T samples."""
    if min(first, second) < window:
        raise ParameterError(f'{name}: its {parts} would have {first} and {second} samples, '
                             f'each needs at least one window of H + T = {window} samples')


def default_config() -> LearnerNodeConfig:
    """The configuration of a learner node started with every parameter at its default."""
    return parse_params({name: spec.default for name, spec in PARAMETERS.items()})


def parse_params(values: Mapping[str, Value]) -> LearnerNodeConfig:
    """Turn raw parameter values (as ROS gives them) into a checked :class:`LearnerNodeConfig`.

    Raises:
        ParameterError: naming the first parameter of the wrong type or out of range.
    """
    meta = build(META, values)
    source = build(SOURCE, values, excitation=build(EXCITATION, values)).resolved()
    family = source.plant_family
    nssm = replace(build(NSSM, values), n_u=family.n_u, n_y=family.n_y)
    return build(NODE, values, meta=meta, nssm=nssm, source=source,
                 online=build(ONLINE, values, seed=meta.seed), adapt=build(ADAPT, values),
                 oracle=build(ORACLE, values), loop=build(LOOP, values),
                 narx=build(NARX, values, n_u=family.n_u, n_y=family.n_y),
                 narx_meta=build(NARX_META, values))


def request_class(request, config: 'LearnerNodeConfig') -> str:
    """The model class a MetaTrain or Adapt request asks for: its ``model_class``, '' the
    node's ``model_class`` parameter.

    Raises:
        ValueError: a class that is not one of MODEL_CLASSES.
    """
    model_class = request.model_class or config.model_class
    if model_class not in MODEL_CLASSES:
        raise ValueError(f'unknown model_class {request.model_class!r}; expected one of '
                         f'{", ".join(repr(c) for c in ("", *MODEL_CLASSES))}')
    return model_class


def resolve_meta_request(request, base: MetaConfig, online_default: bool
                         ) -> Tuple[MetaConfig, bool]:
    """A MetaTrain request (0 / empty: the parameter; gamma <= 0 and init_loss_weight < 0 too)
    -> (checked MetaConfig, online collection).

    Raises:
        ValueError: unknown or non-meta method (supervised), negative rates, ...
    """
    method = request.method or base.method
    if method == 'supervised':
        raise ValueError("'supervised' has no meta-training phase: call adapt with method "
                         "'supervised' to train it on the target buffer")
    if method not in META_METHODS:
        raise ValueError(f'unknown method {method!r}; expected one of '
                         f'{", ".join(META_METHODS)}')
    for name in ('gamma', 'lr_inner', 'lr_outer', 'init_loss_weight'):
        if not math.isfinite(getattr(request, name)):
            raise ValueError(f'{name} must be finite, got {getattr(request, name)}')
    for name in ('lr_inner', 'lr_outer'):
        if getattr(request, name) < 0:
            raise ValueError(f'{name} must be >= 0 (0: parameter), got {getattr(request, name)}')
    config = replace(
        base, method=method, iterations=request.iterations or base.iterations,
        batch_size=request.batch_size or base.batch_size,
        inner_steps=request.inner_steps or base.inner_steps,
        gamma=request.gamma if request.gamma > 0 else base.gamma,
        lr_inner=request.lr_inner or base.lr_inner, lr_outer=request.lr_outer or base.lr_outer,
        cg_steps=request.cg_steps or base.cg_steps, seed=request.seed or base.seed,
        init_loss_weight=(request.init_loss_weight if request.init_loss_weight >= 0
                          else base.init_loss_weight))
    config.validate()
    return config, bool(request.online_collection) or online_default


def resolve_narx_request(request, base: NarxMetaConfig, meta: MetaConfig) -> NarxMetaConfig:
    """A MetaTrain request of a feature NARX learner (model_class feature_narx) -> its checked
    config: `method` ('': the node's ``method``), `iterations`, `batch_size` and `seed` as for
    the NSSM, `lr_outer` its Adam step size and `gamma` (> 0) the inner solve's proximal
    strength (<= 0: ``narx_gamma``); the NSSM's inner-loop fields (`inner_steps`, `lr_inner`,
    `cg_steps`, `init_loss_weight`) mean nothing to its closed-form inner solve and are ignored.

    Raises:
        ValueError: a method it has no meta-training for, online collection, bad rates.
    """
    method = request.method or meta.method
    if method not in NARX_METHODS:
        raise ValueError(f'model_class feature_narx meta-trains with '
                         f'{" or ".join(NARX_METHODS)}, not {method!r}')
    if request.online_collection:
        raise ValueError("online collection is the NSSM's only, not for model_class "
                         'feature_narx')
    for name in ('gamma', 'lr_outer'):
        if not math.isfinite(getattr(request, name)):
            raise ValueError(f'{name} must be finite, got {getattr(request, name)}')
    if request.lr_outer < 0:
        raise ValueError(f'lr_outer must be >= 0 (0: parameter), got {request.lr_outer}')
    config = replace(base, method=method, iterations=request.iterations or base.iterations,
                     batch_size=request.batch_size or base.batch_size,
                     lr=request.lr_outer or base.lr, seed=request.seed or meta.seed,
                     gamma=request.gamma if request.gamma > 0 else base.gamma)
    config.validate()
    return config


@dataclass
class AdaptJob:
    """A resolved Adapt request.

    Attributes:
        method: '' (latest meta-model), a meta method, 'supervised', 'oracle' or 'arx'.
        steps: gradient steps (Adam steps for the oracle).
        lr: step size.
        gamma: proximal strength of eq. infer (>= 0; ignored by supervised and oracle).
        n_samples: buffered samples to use, the first ones (0: all).
        model_class: the class of the model it fits ('': the node's ``model_class``).
    """

    method: str
    steps: int
    lr: float
    gamma: float
    n_samples: int
    model_class: str = ''


def resolve_adapt_request(request, adapt: AdaptConfig, oracle: OracleConfig,
                          model_class: str = '') -> AdaptJob:
    """An Adapt request (0 / empty: the parameter; gamma < 0: the parameter) -> AdaptJob of
    `model_class` (:func:`request_class`; '': the node's).

    Raises:
        ValueError: unknown method, non-finite or negative lr, non-finite gamma.
    """
    method = request.method
    if method not in ('', *ADAPT_METHODS):
        raise ValueError(f'unknown method {method!r}; expected one of '
                         f'{", ".join(repr(m) for m in ("", *ADAPT_METHODS))}')
    if not (math.isfinite(request.lr) and request.lr >= 0):
        raise ValueError(f'lr must be finite and >= 0 (0: parameter), got {request.lr}')
    if not math.isfinite(request.gamma):
        raise ValueError(f'gamma must be finite (< 0: parameter), got {request.gamma}')
    if method == 'oracle':
        steps, lr = request.steps or oracle.steps, request.lr or oracle.lr
    else:
        steps, lr = request.steps or adapt.steps, request.lr or adapt.lr
    gamma = request.gamma if request.gamma >= 0 else adapt.gamma
    return AdaptJob(method, int(steps), float(lr), float(gamma), int(request.n_samples),
                    model_class)


def fit_settings(config: LearnerNodeConfig, job: AdaptJob) -> FitSettings:
    """How ``target_fit.fit_target`` fits `job` on this learner: its steps, lr and gamma on
    the adaptation parameters (the oracle's steps and lr too), the ARX order, the gain check
    on the family's tracked outputs, the meta seed; a feature NARX's ridge strength the job's
    gamma when > 0, else ``narx_gamma``."""
    return FitSettings(
        adapt=replace(config.adapt, steps=job.steps, lr=job.lr, gamma=job.gamma),
        oracle=replace(config.oracle, steps=job.steps, lr=job.lr), arx_order=config.arx_order,
        gain_check=config.gain_check, tracked=tuple(config.source.plant_family.tracked),
        seed=config.meta.seed,
        narx_gamma=job.gamma if job.gamma > 0 else config.narx_meta.gamma,
        narx_horizon=config.narx_meta.horizon)


__all__ = ['PARAMETERS', 'LearnerNodeConfig', 'parse_params', 'request_class',
           'resolve_meta_request',
           'resolve_narx_request', 'AdaptJob', 'resolve_adapt_request', 'fit_settings',
           'default_config', 'ADAPT_METHODS', 'ParameterError']
