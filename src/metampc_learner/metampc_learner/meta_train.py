"""Meta-training (Algorithm 1): the outer loop of iMAML, first-order MAML or unrolled MAML.

Each outer step samples B tasks of the source set, computes their meta-gradients (imaml.py,
maml.py; vmap, a loop, or batched_objective.py on the 'fast' backend) and applies the mean
with Adam: eq. (outer) for iMAML, eq. (outer_maml) for MAML, plus the optional anchor of the
meta-model (``init_loss_weight``), the divergence guard (held-out validation tasks, rollback
to the best checkpoint) and Algorithm 1's online collection (``collector``). In: a
:class:`MetaConfig`, a source set and an NSSM; out: the best checkpoint's weights and the
curves (:class:`MetaResult`). Refuses a bad config (:meth:`MetaConfig.validate`, e.g. 'cuda'
without a CUDA device); skips non-finite tasks, and raises :class:`MetaTrainingError` when too
many are skipped in a row. The same seed, backend, device and thread count give the same
weights. Details and measurements: docs/learning.md.
"""
import copy
import math
import time
from dataclasses import dataclass, field
from typing import Callable, List, Optional, Sequence, Set, Tuple

import numpy as np
import torch
from torch.func import grad, vmap

from metampc_common.params import check_fields, param, ParameterError
from metampc_model.nssm import init_params, Nssm, Params
from metampc_learner.batched_objective import BatchedNssm, BatchedTaskGradient
from metampc_learner.curvature import CURVATURES
from metampc_learner.data import SourceSet, Trajectory
from metampc_learner.imaml import ImamlTaskGradient
from metampc_learner.maml import FirstOrderMamlTaskGradient, UnrolledMamlTaskGradient
from metampc_learner.objective import FlatObjective
from metampc_learner.progress import Progress, ProgressFn
from metampc_learner.task_gradient import TaskGradient

META_METHODS = ('imaml', 'maml', 'maml_unrolled')
LR_SCHEDULES = ('constant', 'cosine')
BACKENDS = ('fast', 'eager')
DEVICES = ('cpu', 'cuda')
Collector = Callable[[int, float, Params], Sequence[Trajectory]]


class MetaTrainingError(RuntimeError):
    """Meta-training stopped because too many tasks kept turning non-finite."""


@dataclass
class MetaConfig:
    """Hyperparameters of meta-training (defaults: the calibration, docs/architecture.md).

    Attributes:
        method: 'imaml', 'maml' (first-order) or 'maml_unrolled' (second-order).
        iterations: outer steps.
        batch_size: B, tasks per outer step.
        inner_steps: M.
        lr_inner: beta_in.
        lr_outer: beta_out (Adam), the initial rate.
        lr_schedule: 'cosine' (beta_out annealed to 0 over the outer steps) or 'constant'.
        gamma: proximal strength of eq. (inner_imaml) (iMAML only).
        cg_steps: CG iterations for eq. (cg) (iMAML only).
        curvature: 'gauss_newton' (default, PSD) or 'hessian' (iMAML only).
        windows_per_task: windows sampled from each of D_tr and D_test per task and step.
        vectorise: eager backend: vmap over the B tasks (True, measured faster) or a Python
            loop.
        backend: 'fast' (batched_objective.py, for iMAML-GN and first-order MAML) or
            'eager' (the vmapped reference; every method).
        device: 'cpu' or 'cuda' (ValueError from validate() when CUDA is absent).
        init_loss_weight: w of the meta-model anchor (module docstring; 0: eq. (outer) as
            written).
        seed: seed of the initial weights and of task/window sampling.
        max_skip_fraction: a step is bad when more than this share of its tasks is skipped.
        max_bad_steps: consecutive bad steps that stop training.
        validation_tasks: source tasks held out for the divergence guard (0: no guard).
        validation_every: outer steps between validations.
        spike_factor: a validation loss above this multiple of the best rolls back.
        rollback_lr_factor: beta_out multiplier at each rollback.
    """

    method: str = param('imaml', 'meta-training method', choices=META_METHODS, live=True)
    iterations: int = param(300, 'outer steps', ge=1, live=True)
    batch_size: int = param(16, 'B, tasks per outer step', ge=1, live=True)
    inner_steps: int = param(10, 'M, inner gradient steps', ge=0, live=True)
    lr_inner: float = param(0.05, 'beta_in, inner step size', ge=0, live=True)
    lr_outer: float = param(1e-3, 'beta_out, initial Adam step size', gt=0, live=True)
    lr_schedule: str = param('constant', 'beta_out over the outer steps (cosine: annealed to '
                                         '0)', choices=LR_SCHEDULES)
    gamma: float = param(1.0, 'proximal strength of eq. inner_imaml', gt=0, live=True)
    cg_steps: int = param(5, 'CG iterations of eq. cg', ge=0, live=True)
    curvature: str = param('gauss_newton', 'iMAML curvature', choices=CURVATURES)
    windows_per_task: int = param(64, 'windows of D_tr and of D_test per task and step', ge=1)
    init_loss_weight: float = param(0.0, 'w: weight of the meta-model loss before adaptation '
                                         'in the outer objective (0: eq. outer as written)',
                                    ge=0, live=True)
    vectorise: bool = True
    backend: str = param('fast', 'meta-gradient code: fast (hand-batched, iMAML with '
                                 'gauss_newton and first-order MAML; the others run eager) or '
                                 'eager (vmap of the per-task reference)', choices=BACKENDS)
    device: str = param('cpu', 'where meta-training runs (cuda: refused when torch sees no '
                               'CUDA device)', choices=DEVICES)
    seed: int = param(0, 'seed of initial weights, task sampling, collection and the '
                         'supervised/oracle initialisation', ge=0, live=True)
    validation_tasks: int = param(8, 'source tasks held out to validate on every '
                                     'validation_every steps (0: no divergence guard)', ge=0)
    validation_every: int = param(10, 'outer steps between validations', ge=1)
    spike_factor: float = param(10.0, 'a validation loss above this multiple of the best (or '
                                      'non-finite) rolls back to the best checkpoint', gt=1)
    rollback_lr_factor: float = param(0.5, 'beta_out multiplier at each rollback', gt=0, lt=1)
    max_skip_fraction: float = 0.5
    max_bad_steps: int = 3

    def validate(self) -> None:
        """Raise ValueError (a ParameterError) naming the first field that is out of range."""
        check_fields(self)
        if self.max_bad_steps < 1:
            raise ValueError(f'max_bad_steps must be >= 1, got {self.max_bad_steps}')
        if self.device == 'cuda' and not torch.cuda.is_available():
            raise ParameterError(f'device must be cpu here: cuda was asked but torch '
                                 f'{torch.__version__} sees no CUDA device')

    @property
    def fast(self) -> bool:
        """Whether the fast backend computes this configuration's meta-gradients."""
        return self.backend == 'fast' and (
            self.method == 'maml' or (self.method == 'imaml'
                                      and self.curvature == 'gauss_newton'))


@dataclass
class MetaResult:
    """Outcome of meta-training.

    Attributes:
        params: the meta-trained weights omega_inf.
        losses: mean meta-test loss l_SSM(D_test; omega_b) per outer step (normalised units).
        cg_residuals: mean relative CG residual per outer step (NaN for MAML).
        lr_outer: beta_out of each outer step.
        skipped: tasks skipped in all.
        collected_samples: collected samples held in the source set at the end.
        dropped_samples: collected samples dropped by the cap.
        elapsed: wall time, s.
        validation_losses: (outer step, validation loss) of each validation.
        best_iteration: outer step of the returned weights (the best validation; the last
            step without the guard).
        rollbacks: outer steps at which a spike rolled training back.
    """

    params: Params
    losses: List[float] = field(default_factory=list)
    cg_residuals: List[float] = field(default_factory=list)
    lr_outer: List[float] = field(default_factory=list)
    skipped: int = 0
    collected_samples: int = 0
    dropped_samples: int = 0
    elapsed: float = 0.0
    validation_losses: List[Tuple[int, float]] = field(default_factory=list)
    best_iteration: int = 0
    rollbacks: List[int] = field(default_factory=list)


@dataclass
class AnchoredTaskGradient:
    """A task's meta-gradient plus weight * grad_omega l_SSM(D_test; omega) (the anchor)."""

    task_fn: Callable[..., TaskGradient]
    objective: FlatObjective
    weight: float

    def __call__(self, omega: torch.Tensor, tr_u: torch.Tensor, tr_y: torch.Tensor,
                 te_u: torch.Tensor, te_y: torch.Tensor) -> TaskGradient:
        out = self.task_fn(omega, tr_u, tr_y, te_u, te_y)
        anchor = grad(self.objective.loss)(omega, te_u, te_y)
        return out._replace(grad=out.grad + self.weight * anchor)


def task_gradient_fn(objective: FlatObjective, config: MetaConfig
                     ) -> Callable[..., TaskGradient]:
    """The per-task meta-gradient of the configured method (anchored when w > 0)."""
    if config.method == 'imaml':
        task_fn = ImamlTaskGradient(objective, config.inner_steps, config.lr_inner,
                                    config.gamma, config.cg_steps, config.curvature)
    elif config.method == 'maml':
        task_fn = FirstOrderMamlTaskGradient(objective, config.inner_steps, config.lr_inner)
    else:
        task_fn = UnrolledMamlTaskGradient(objective, config.inner_steps, config.lr_inner)
    if config.init_loss_weight > 0:
        return AnchoredTaskGradient(task_fn, objective, config.init_loss_weight)
    return task_fn


def batch_gradient_fn(objective: FlatObjective, config: MetaConfig
                      ) -> Callable[..., TaskGradient]:
    """(omega (P,), tr_u, tr_y, te_u, te_y with a leading B) -> TaskGradient batched over B.

    The fast backend (batched_objective.py) where it covers the configuration (l_SSM alone, not
    the NSSM's latent consistency term), its result on ``config.device``; else the reference,
    vmapped (``vectorise``) or looped, on the device of its arguments.
    """
    if config.fast and not objective.model.config.consistency_weight:
        return BatchedTaskGradient(BatchedNssm(objective.model, config.device), config.method,
                                   config.inner_steps, config.lr_inner, config.gamma,
                                   config.cg_steps, config.init_loss_weight)
    task_fn = task_gradient_fn(objective, config)
    if config.vectorise:
        return vmap(task_fn, in_dims=(None, 0, 0, 0, 0))

    def loop(omega, tr_u, tr_y, te_u, te_y):
        outs = [task_fn(omega, *(x[b] for x in (tr_u, tr_y, te_u, te_y)))
                for b in range(tr_u.shape[0])]
        return TaskGradient(*(torch.stack(parts) for parts in zip(*outs)))

    return loop


class DivergenceGuard:
    """The held-out tasks, their fixed windows, the best checkpoint and the rollbacks (module
    docstring). ``tasks`` are excluded from training; check() runs at validation steps."""

    def __init__(self, source: SourceSet, config: MetaConfig, batch_fn, device):
        # At most a fifth of the tasks: the rest must still train (a source set of fewer than
        # five tasks has no guard).
        n_val = min(config.validation_tasks, len(source) // 5)
        rng = np.random.default_rng([config.seed, 0x7a11d])
        self.tasks = np.sort(rng.choice(len(source), size=max(n_val, 0), replace=False))
        self.config, self._batch_fn = config, batch_fn
        self.best = (float('inf'), 0, None, None)     # (loss, step, omega, Adam state)
        if len(self.tasks):
            train, test = source.sample(self.tasks, config.windows_per_task, rng)
            self._windows = tuple(x.to(device) for x in (train.u, train.y, test.u, test.y))

    @property
    def on(self) -> bool:
        return len(self.tasks) > 0

    def loss(self, omega: torch.Tensor) -> float:
        """Mean meta-test loss of the held-out tasks at omega (non-finite tasks: inf)."""
        out = self._batch_fn(omega.detach(), *self._windows)
        losses = out.test_loss
        return float(losses.mean()) if bool(torch.isfinite(losses).all()) else float('inf')

    def check(self, it: int, omega: torch.nn.Parameter, optimiser, result: 'MetaResult'
              ) -> None:
        """Validate at step `it`: keep a new best, or roll back on a spike."""
        loss = self.loss(omega)
        result.validation_losses.append((it, loss))
        best_loss, _, best_omega, best_state = self.best
        if math.isfinite(loss) and loss <= best_loss:
            self.best = (loss, it, omega.detach().clone(), copy.deepcopy(optimiser.state_dict()))
        elif best_omega is not None and (not math.isfinite(loss)
                                         or loss > self.config.spike_factor * best_loss):
            with torch.no_grad():
                omega.copy_(best_omega)
            optimiser.load_state_dict(best_state)
            for group in optimiser.param_groups:
                group['lr'] *= self.config.rollback_lr_factor
            # The next rollback, if any, also starts from the smaller step.
            self.best = (best_loss, self.best[1], best_omega,
                         copy.deepcopy(optimiser.state_dict()))
            result.rollbacks.append(it)


def meta_train(model: Nssm, source: SourceSet, config: MetaConfig,
               progress: Optional[ProgressFn] = None, collector: Optional[Collector] = None,
               init: Optional[Params] = None) -> MetaResult:
    """Run Algorithm 1 and return omega_inf.

    Args:
        model: the NSSM (architecture and normalisation; its own weights are not used).
        source: the tasks (grows when a collector is given).
        config: hyperparameters.
        progress: called after every outer step.
        collector: Algorithm 1's online collection, see the module docstring.
        init: initial weights; default init_params(model.config, config.seed).

    Raises:
        MetaTrainingError: too many non-finite tasks for too long.
    """
    config.validate()
    objective = FlatObjective(model)
    dtype = next(model.parameters()).dtype
    device = torch.device(config.device)
    if init is None:
        init = init_params(model.config, config.seed, dtype)
    omega = torch.nn.Parameter(objective.spec.flatten(init).detach().clone().to(device))
    optimiser = torch.optim.Adam([omega], lr=config.lr_outer)
    schedule = (torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, config.iterations)
                if config.lr_schedule == 'cosine' else None)
    batch_fn = batch_gradient_fn(objective, config)
    rng = np.random.default_rng(config.seed)
    result = MetaResult(params={})
    guard = DivergenceGuard(source, config, batch_fn, device)
    train_tasks = np.setdiff1d(np.arange(len(source)), guard.tasks)
    if guard.on:
        guard.check(0, omega, optimiser, result)
    bad_steps = 0
    bad_tasks: Set[int] = set()
    start = time.monotonic()
    for it in range(1, config.iterations + 1):
        tasks = rng.choice(train_tasks, size=config.batch_size,
                           replace=len(train_tasks) < config.batch_size)
        train, test = source.sample(tasks, config.windows_per_task, rng)
        windows = (x.to(device) for x in (train.u, train.y, test.u, test.y))
        out = batch_fn(omega.detach(), *windows)
        ok = torch.isfinite(out.test_loss) & torch.isfinite(out.grad).all(dim=-1)
        result.lr_outer.append(optimiser.param_groups[0]['lr'])
        n_bad = int((~ok).sum())
        result.skipped += n_bad
        if ok.any():
            omega.grad = out.grad[ok].mean(dim=0)
            optimiser.step()
            optimiser.zero_grad(set_to_none=True)
        if schedule is not None:
            schedule.step()
        if n_bad > config.max_skip_fraction * config.batch_size:
            bad_steps += 1
            bad_tasks.update(int(tasks[b]) for b in torch.nonzero(~ok).flatten().tolist())
            if bad_steps >= config.max_bad_steps:
                names = ', '.join(f'{t} (system {source.system_index[t]}, theta='
                                  f'{np.round(source.thetas[t], 3).tolist()})'
                                  for t in sorted(bad_tasks))
                raise MetaTrainingError(
                    f'{config.method}: more than {config.max_skip_fraction:.0%} of the batch '
                    f'non-finite for {bad_steps} consecutive steps (up to step {it}); '
                    f'skipped tasks: {names}')
        else:
            bad_steps = 0
            bad_tasks = set()
        if collector is not None:
            for b in torch.nonzero(ok).flatten().tolist():
                task = int(tasks[b])
                adapted = out.adapted[b].detach().to('cpu', copy=True)
                new = collector(task, source.thetas[task], objective.spec.unflatten(adapted))
                source.add(task, new)
        loss = float(out.test_loss[ok].mean()) if ok.any() else float('nan')
        residual = float(out.cg_residual[ok].mean()) if ok.any() else float('nan')
        result.losses.append(loss)
        result.cg_residuals.append(residual)
        if guard.on and (it % config.validation_every == 0 or it == config.iterations):
            guard.check(it, omega, optimiser, result)
        if progress is not None:
            progress(Progress(it, config.iterations, loss, time.monotonic() - start,
                              result.skipped, residual,
                              result.validation_losses[-1][1] if guard.on else math.nan,
                              len(result.rollbacks), guard.best[1] if guard.on else it))
    final = guard.best[2] if guard.on and guard.best[2] is not None else omega.detach()
    result.best_iteration = guard.best[1] if guard.on else config.iterations
    result.params = {k: v.detach().cpu().clone()
                     for k, v in objective.spec.unflatten(final).items()}
    result.collected_samples = source.collected_samples
    result.dropped_samples = source.dropped_samples
    result.elapsed = time.monotonic() - start
    return result
