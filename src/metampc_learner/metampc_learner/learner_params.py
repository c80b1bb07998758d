"""Parameters of the `learner` node and its service requests: names, defaults, range checks.

Pure Python (no rclpy), so the checks are testable alone. The node declares every entry of
:data:`PARAMETERS`, hands the values to :func:`parse_params` and exits with one error line
(status 2) if that raises :class:`ParameterError`. Requests of ``meta_train`` and ``adapt``
are resolved against the parameters by :func:`resolve_meta_request` and
:func:`resolve_adapt_request` (0 / empty fields mean 'use the node parameter'); they raise
``ValueError`` with the reason for a bad request.

Defaults are the calibration of docs/architecture.md (B = 16, M = 10 at lr 0.05, 5 CG steps with
Gauss-Newton curvature, Adam 1e-3, 64 windows per task, 20 plain adaptation steps at lr 0.05)
and the paper's NSSM (n_z = 5, 128-wide ReLU layers).
"""
import math
from dataclasses import dataclass, field, replace
from typing import Dict, Mapping, Tuple

from metampc_common.params import number, ParameterError, ParamSpec, Value
from metampc_controller.excitation import ExcitationConfig, KINDS
from metampc_controller.nssm import NssmConfig
from metampc_learner.adapt import AdaptConfig
from metampc_learner.curvature import CURVATURES
from metampc_learner.data import SourceConfig
from metampc_learner.meta_train import LR_SCHEDULES, MetaConfig, METHODS
from metampc_learner.online_collection import OnlineCollectionConfig
from metampc_learner.oracle import OracleConfig

ADAPT_METHODS = ('', *METHODS, 'supervised', 'oracle')

_META, _NSSM, _SRC, _EXC = MetaConfig(), NssmConfig(), SourceConfig(), ExcitationConfig()
_ONLINE, _ADAPT, _ORACLE = OnlineCollectionConfig(), AdaptConfig(), OracleConfig()

PARAMETERS: Dict[str, ParamSpec] = {
    # Meta-training (Algorithm 1); the defaults of meta_train requests.
    'method': ParamSpec(_META.method, f'meta-training method: {", ".join(METHODS)}'),
    'iterations': ParamSpec(_META.iterations, 'outer steps (>= 1)'),
    'batch_size': ParamSpec(_META.batch_size, 'B, tasks per outer step (>= 1)'),
    'inner_steps': ParamSpec(_META.inner_steps, 'M, inner gradient steps (>= 0)'),
    'gamma': ParamSpec(_META.gamma, 'proximal strength of eq. inner_imaml (> 0)'),
    'lr_inner': ParamSpec(_META.lr_inner, 'beta_in, inner step size (>= 0)'),
    'lr_outer': ParamSpec(_META.lr_outer, 'beta_out, initial Adam step size (> 0)'),
    'lr_schedule': ParamSpec(_META.lr_schedule, 'beta_out over the outer steps: '
                             f'{", ".join(LR_SCHEDULES)} (cosine: annealed to 0)'),
    'cg_steps': ParamSpec(_META.cg_steps, 'CG iterations of eq. cg (>= 0)'),
    'curvature': ParamSpec(_META.curvature, f'iMAML curvature: {", ".join(CURVATURES)}'),
    'windows_per_task': ParamSpec(_META.windows_per_task,
                                  'windows of D_tr and of D_test per task and step (>= 1)'),
    'seed': ParamSpec(_META.seed, 'seed of initial weights, task sampling, collection and '
                      'the supervised/oracle initialisation (>= 0)'),
    # The NSSM (eq. SSM).
    'n_z': ParamSpec(_NSSM.n_z, 'latent dimension (>= 1)'),
    'history': ParamSpec(_NSSM.history, 'H, samples the encoder reads (>= 1)'),
    'horizon': ParamSpec(_NSSM.horizon, 'T, prediction steps of the loss (>= 1)'),
    'hidden': ParamSpec(list(_NSSM.hidden), 'widths of the encoder ReLU layers (each >= 1)'),
    'stable_latent': ParamSpec(_NSSM.stable_latent, 'bound the spectral norm of A by rho_max '
                               '(false: A free, as in the paper)'),
    'rho_max': ParamSpec(_NSSM.rho_max, 'bound of the spectral norm of A (> 0)'),
    # Simulated source systems (also the simulator of online collection and the oracle).
    'n_systems': ParamSpec(_SRC.n_systems, 'N_s, source systems (>= 1)'),
    'episodes_per_system': ParamSpec(_SRC.episodes_per_system, 'episodes per system (>= 1)'),
    'episode_samples': ParamSpec(_SRC.episode_samples, 'samples per episode (>= 2)'),
    'dt': ParamSpec(_SRC.dt, 'sample time, s (> 0); must equal the plant\'s'),
    'substeps': ParamSpec(_SRC.substeps, 'RK4 steps per sample (>= 1)'),
    'theta_mean': ParamSpec(_SRC.theta_mean, 'mean of Theta = N(mean, std^2)'),
    'theta_std': ParamSpec(_SRC.theta_std, 'std of Theta (>= 0)'),
    'x0_bound': ParamSpec(_SRC.x0_bound, 'initial states uniform in [-b, b]^2 (>= 0)'),
    'state_bound': ParamSpec(_SRC.state_bound, 'episodes end when |x|_inf exceeds this; '
                             'target samples beyond it are dropped (> 0)'),
    'u_min': ParamSpec(_EXC.u_min, 'input lower bound of the simulated systems'),
    'u_max': ParamSpec(_EXC.u_max, 'input upper bound of the simulated systems'),
    'excitation': ParamSpec(_EXC.kind, f'source excitation: {", ".join(KINDS)}'),
    'hold_s': ParamSpec(_EXC.hold_s, 'excitation hold time, s (> 0)'),
    'source_seed': ParamSpec(_SRC.seed, 'seed of the source systems and their data (>= 0)'),
    'train_fraction': ParamSpec(0.5, 'share (in time) of each source episode in D_tr, (0, 1)'),
    # Algorithm 1's online collection (eq. ub).
    'online_collection': ParamSpec(False, 'collect closed-loop source data during '
                                          'meta-training (a request can also turn it on)'),
    'online_episodes': ParamSpec(_ONLINE.episodes, 'episodes per task and outer step (>= 1)'),
    'online_samples': ParamSpec(_ONLINE.episode_samples,
                                'closed-loop samples per episode after H warm-up (>= 1)'),
    'online_noise_std': ParamSpec(_ONLINE.noise_std, 'exploration std of eq. ub (>= 0)'),
    'online_max_samples': ParamSpec(20000, 'cap of collected samples kept (>= 1)'),
    'online_horizon': ParamSpec(_ONLINE.horizon, 'MPC horizon N of the collection (>= 1)'),
    'online_r': ParamSpec(_ONLINE.r, 'MPC Delta-u weight of the collection (> 0)'),
    'online_ref_bound': ParamSpec(_ONLINE.ref_bound, 'x1 set-points uniform in [-b, b] (>= 0)'),
    'online_ref_hold_s': ParamSpec(_ONLINE.ref_hold_s, 'set-point hold time, s (> 0)'),
    # Target data (D_target) and adaptation (eq. infer).
    'target_buffer_size': ParamSpec(300, 'target samples kept after buffering (re)starts '
                                         '(>= 1)'),
    'buffer_on_start': ParamSpec(True, 'buffer y from the start (false: only after '
                                       'set_buffering true)'),
    'heldout_fraction': ParamSpec(0.2, 'last share of the buffered samples held out for the '
                                       'loss curve, (0, 1)'),
    'adapt_steps': ParamSpec(_ADAPT.steps, 'adaptation gradient steps (>= 0)'),
    'adapt_lr': ParamSpec(_ADAPT.lr, 'adaptation step size (> 0)'),
    'adapt_gamma': ParamSpec(_ADAPT.gamma, 'proximal strength of eq. infer (>= 0; 0: plain '
                                           'gradient steps)'),
    'oracle_episodes': ParamSpec(_ORACLE.episodes, 'simulated target episodes of the oracle '
                                                   '(>= 1)'),
    'oracle_steps': ParamSpec(_ORACLE.steps, 'oracle Adam steps (>= 0)'),
    'oracle_lr': ParamSpec(_ORACLE.lr, 'oracle Adam step size (> 0)'),
    'oracle_batch': ParamSpec(_ORACLE.batch_windows, 'oracle windows per Adam step (>= 1)'),
    # Files and run time.
    'meta_model_path': ParamSpec('', 'checkpoint to load at start and publish as stage meta '
                                     "('': none)"),
    'checkpoint_dir': ParamSpec('', "directory for checkpoints of every trained model ('': "
                                    'none; created if missing)'),
    'torch_threads': ParamSpec(1, 'torch intra-op threads (>= 1; see docs/learner.md)'),
    'progress_period': ParamSpec(0.5, 'progress heartbeat while training, s (> 0, <= 1)'),
}


@dataclass
class LearnerNodeConfig:
    """Everything the learner node is configured with.

    Attributes:
        meta: meta-training defaults (Algorithm 1).
        nssm: architecture of new models.
        source: simulated source systems.
        online: closed-loop collection settings (eq. ub).
        online_collection: collect by default.
        online_max_samples: cap of collected samples in the source set.
        train_fraction: share of each source episode in D_tr.
        target_buffer_size: capacity of D_target, samples.
        buffer_on_start: buffer y from the start (else only after set_buffering true).
        heldout_fraction: last share of D_target held out for loss curves.
        adapt: adaptation defaults (eq. infer).
        oracle: oracle settings.
        meta_model_path: checkpoint to load at start ('' none).
        checkpoint_dir: where checkpoints go ('' none).
        torch_threads: torch intra-op threads.
        progress_period: heartbeat period of `progress` while training, s.
    """

    meta: MetaConfig = field(default_factory=MetaConfig)
    nssm: NssmConfig = field(default_factory=NssmConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    online: OnlineCollectionConfig = field(default_factory=OnlineCollectionConfig)
    online_collection: bool = False
    online_max_samples: int = 20000
    train_fraction: float = 0.5
    target_buffer_size: int = 300
    buffer_on_start: bool = True
    heldout_fraction: float = 0.2
    adapt: AdaptConfig = field(default_factory=AdaptConfig)
    oracle: OracleConfig = field(default_factory=OracleConfig)
    meta_model_path: str = ''
    checkpoint_dir: str = ''
    torch_threads: int = 1
    progress_period: float = 0.5


def _check(ok: bool, text: str) -> None:
    if not ok:
        raise ParameterError(text)


def _checked(make):
    """Build a core config and run its own validation; its ValueError as a ParameterError."""
    try:
        config = make()
        config.validate()
        return config
    except ValueError as err:
        raise ParameterError(str(err)) from None


def _check_split(name: str, first: int, second: int, window: int, parts: str) -> None:
    """Both parts of a split must hold at least one window of H + T samples."""
    _check(min(first, second) >= window,
           f'{name}: its {parts} would have {first} and {second} samples, each needs at least '
           f'one window of H + T = {window} samples')


def parse_params(values: Mapping[str, Value]) -> LearnerNodeConfig:
    """Turn raw parameter values (as ROS gives them) into a checked :class:`LearnerNodeConfig`.

    Raises:
        ParameterError: naming the first parameter of the wrong type or out of range.
    """
    num = {name: number(name, values[name], integer=isinstance(spec.default, int))
           for name, spec in PARAMETERS.items()
           if isinstance(spec.default, (int, float)) and not isinstance(spec.default, bool)}
    for name, value in num.items():
        _check(math.isfinite(value), f'{name} must be finite, got {value}')
    text = {name: values[name] for name, spec in PARAMETERS.items()
            if isinstance(spec.default, str)}
    for name, value in text.items():
        _check(isinstance(value, str), f'{name} must be a string, got {value!r}')
    flags = {name: values[name] for name, spec in PARAMETERS.items()
             if isinstance(spec.default, bool)}
    for name, value in flags.items():
        _check(isinstance(value, bool), f'{name} must be true or false, got {value!r}')
    hidden = values['hidden']
    _check(not isinstance(hidden, (str, bool)) and hasattr(hidden, '__len__'),
           f'hidden must be a list of integers, got {hidden!r}')
    hidden = tuple(number('hidden', w, integer=True) for w in hidden)
    for name in ('iterations', 'batch_size', 'windows_per_task', 'n_systems',
                 'episodes_per_system', 'online_max_samples', 'target_buffer_size',
                 'oracle_episodes', 'oracle_batch', 'torch_threads', 'online_episodes',
                 'online_samples', 'online_horizon'):
        _check(num[name] >= 1, f'{name} must be >= 1, got {num[name]}')
    for name in ('inner_steps', 'cg_steps', 'seed', 'source_seed', 'adapt_steps',
                 'oracle_steps', 'theta_std', 'x0_bound', 'lr_inner', 'adapt_gamma',
                 'online_noise_std', 'online_ref_bound'):
        _check(num[name] >= 0, f'{name} must be >= 0, got {num[name]}')
    for name in ('gamma', 'lr_outer', 'dt', 'state_bound', 'adapt_lr', 'oracle_lr', 'online_r',
                 'online_ref_hold_s', 'hold_s'):
        _check(num[name] > 0, f'{name} must be > 0, got {num[name]}')
    _check(num['episode_samples'] >= 2,
           f'episode_samples must be >= 2, got {num["episode_samples"]}')
    _check(0 < num['progress_period'] <= 1.0,
           f'progress_period must be in (0, 1] s, got {num["progress_period"]}')
    for name in ('train_fraction', 'heldout_fraction'):
        _check(0 < num[name] < 1, f'{name} must be in (0, 1), got {num[name]}')
    _check(text['method'] in METHODS,
           f'method must be one of {", ".join(METHODS)}, got {text["method"]!r}')
    nssm = _checked(lambda: NssmConfig(n_z=num['n_z'], history=num['history'], hidden=hidden,
                                       horizon=num['horizon'],
                                       stable_latent=flags['stable_latent'],
                                       rho_max=num['rho_max']))
    meta = _checked(lambda: MetaConfig(
        method=text['method'], iterations=num['iterations'], batch_size=num['batch_size'],
        inner_steps=num['inner_steps'], lr_inner=num['lr_inner'], lr_outer=num['lr_outer'],
        lr_schedule=text['lr_schedule'], gamma=num['gamma'], cg_steps=num['cg_steps'],
        curvature=text['curvature'],
        windows_per_task=num['windows_per_task'], seed=num['seed']))
    exc = _checked(lambda: ExcitationConfig(kind=text['excitation'], u_min=num['u_min'],
                                            u_max=num['u_max'], hold_s=num['hold_s']))
    source = SourceConfig(
        n_systems=num['n_systems'], episodes_per_system=num['episodes_per_system'],
        episode_samples=num['episode_samples'], dt=num['dt'], substeps=num['substeps'],
        theta_mean=num['theta_mean'], theta_std=num['theta_std'], x0_bound=num['x0_bound'],
        state_bound=num['state_bound'], excitation=exc, seed=num['source_seed'])
    _check(source.substeps >= 1, f'substeps must be >= 1, got {source.substeps}')
    _check(source.x0_bound <= source.state_bound,
           f'x0_bound {source.x0_bound} exceeds state_bound {source.state_bound}')
    d_tr = int(round(num['train_fraction'] * source.episode_samples))
    _check_split('episode_samples', d_tr, source.episode_samples - d_tr, nssm.window,
                 'D_tr / D_test parts (train_fraction)')
    held = int(round(num['heldout_fraction'] * num['target_buffer_size']))
    _check_split('target_buffer_size', num['target_buffer_size'] - held, held, nssm.window,
                 'training / held-out parts (heldout_fraction)')
    online = _checked(lambda: OnlineCollectionConfig(
        episodes=num['online_episodes'], episode_samples=num['online_samples'],
        noise_std=num['online_noise_std'], horizon=num['online_horizon'], r=num['online_r'],
        ref_bound=num['online_ref_bound'], ref_hold_s=num['online_ref_hold_s'],
        seed=num['seed']))
    adapt = _checked(lambda: AdaptConfig(num['adapt_steps'], num['adapt_lr'],
                                         num['adapt_gamma']))
    oracle = _checked(lambda: OracleConfig(
        episodes=num['oracle_episodes'], steps=num['oracle_steps'], lr=num['oracle_lr'],
        batch_windows=num['oracle_batch']))
    return LearnerNodeConfig(
        meta=meta, nssm=nssm, source=source, online=online,
        online_collection=flags['online_collection'],
        online_max_samples=num['online_max_samples'], train_fraction=num['train_fraction'],
        target_buffer_size=num['target_buffer_size'], buffer_on_start=flags['buffer_on_start'],
        heldout_fraction=num['heldout_fraction'], adapt=adapt, oracle=oracle,
        meta_model_path=text['meta_model_path'], checkpoint_dir=text['checkpoint_dir'],
        torch_threads=num['torch_threads'], progress_period=num['progress_period'])


def resolve_meta_request(request, base: MetaConfig, online_default: bool
                         ) -> Tuple[MetaConfig, bool]:
    """A MetaTrain request (0 / empty: the parameter) -> (checked MetaConfig, online collection).

    Raises:
        ValueError: unknown or non-meta method (supervised), negative rates, ...
    """
    method = request.method or base.method
    if method == 'supervised':
        raise ValueError("'supervised' has no meta-training phase: call adapt with method "
                         "'supervised' to train it on the target buffer")
    if method not in METHODS:
        raise ValueError(f'unknown method {method!r}; expected one of {", ".join(METHODS)}')
    for name in ('gamma', 'lr_inner', 'lr_outer'):
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
        cg_steps=request.cg_steps or base.cg_steps, seed=request.seed or base.seed)
    config.validate()
    return config, bool(request.online_collection) or online_default


@dataclass
class AdaptJob:
    """A resolved Adapt request.

    Attributes:
        method: '' (latest meta-model), a meta method, 'supervised' or 'oracle'.
        steps: gradient steps (Adam steps for the oracle).
        lr: step size.
        gamma: proximal strength of eq. infer (>= 0; ignored by supervised and oracle).
        n_samples: buffered samples to use, the first ones (0: all).
    """

    method: str
    steps: int
    lr: float
    gamma: float
    n_samples: int


def resolve_adapt_request(request, adapt: AdaptConfig, oracle: OracleConfig) -> AdaptJob:
    """An Adapt request (0 / empty: the parameter; gamma < 0: the parameter) -> AdaptJob.

    Raises:
        ValueError: unknown method, non-finite or negative lr, non-finite gamma.
    """
    method = request.method
    if method not in ADAPT_METHODS:
        raise ValueError(f'unknown method {method!r}; expected one of '
                         f'{", ".join(repr(m) for m in ADAPT_METHODS)}')
    if not (math.isfinite(request.lr) and request.lr >= 0):
        raise ValueError(f'lr must be finite and >= 0 (0: parameter), got {request.lr}')
    if not math.isfinite(request.gamma):
        raise ValueError(f'gamma must be finite (< 0: parameter), got {request.gamma}')
    if method == 'oracle':
        steps, lr = request.steps or oracle.steps, request.lr or oracle.lr
    else:
        steps, lr = request.steps or adapt.steps, request.lr or adapt.lr
    gamma = request.gamma if request.gamma >= 0 else adapt.gamma
    return AdaptJob(method, int(steps), float(lr), float(gamma), int(request.n_samples))


__all__ = ['PARAMETERS', 'LearnerNodeConfig', 'parse_params', 'resolve_meta_request',
           'AdaptJob', 'resolve_adapt_request', 'ADAPT_METHODS', 'ParameterError']
