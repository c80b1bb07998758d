"""Meta-training and adaptation of the feature NARX (:mod:`metampc_model.feature_narx`).

Adaptation (Algorithm 2, eq. (infer) solved exactly): g stays the meta-model's, the head is the
closed-form ridge fit toward the meta-model's head on the target's one-step equations; never a
higher training loss than the least-squares ARX(p) of the same samples (:func:`adapt`: toward
the ARX's head instead, if it would be). Meta-training, per outer step B source systems, each
task's head solved in closed form: 'imaml' (eqs. (outer), (inner_imaml)) the T-step rollout
loss on D_test through the solve on D_tr (the exact implicit meta-gradient); 'maml' first order
by variable projection, the inner objective itself at the solved head, whose partial gradient
is the exact one there (the envelope theorem). Measured: docs/nonlinear.md.
"""
from dataclasses import dataclass, field
import math
import time
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np
import torch

from metampc_common.params import param
from metampc_learner.closed_form import mean_loss, ridge
from metampc_model.feature_narx import (FeatureNarx, init_params, NarxShape, Params,
                                        regressors, rollout, state_windows)
from metampc_model.normalisation import Normalisation

Record = Tuple[np.ndarray, np.ndarray]     # (u (K, n_u), y (K, n_y)) physical, u[k] -> y[k]
# adapt's validation in time: the share of each record held back, and its rollout horizon.
VALIDATION_SHARE = 1.0 / 3.0
VALIDATION_HORIZON = 10
NARX_METHODS = ('imaml', 'maml')


@dataclass
class NarxMetaConfig:
    """Attributes (the numbers are also the learner's node parameters ``narx_<name>``):
        method: 'imaml' (exact meta-gradient through the solve) or 'maml' (first order, by
            variable projection: :func:`outer_loss`).
        iterations: outer steps.
        batch_size: B, source systems per step.
        windows: windows drawn per system per step, for D_tr and for D_test each.
        horizon: T of the outer (D_test) rollout loss, samples.
        lr: Adam step size.
        gamma: proximal strength of the closed-form inner solve (mean-loss units), in
            either method's meta-training and in the adaptation to the target.
        seed: initial weights and the draws of systems and windows.

    Defaults: the van der Pol calibration of docs/nonlinear.md (gamma 1e-3 made the prior
    dominate the target's samples: the ridge fit lost to the ARX and fell back to least
    squares; 400 steps left the D_test loss at 8e-4 against 6e-5 after 1000).
    """

    method: str = 'imaml'
    iterations: int = param(1000, 'outer steps of feature NARX meta-training', ge=1)
    batch_size: int = param(16, 'B, source systems per outer step', ge=1)
    windows: int = param(64, 'windows drawn per source system and step, for D_tr and D_test '
                             'each', ge=1)
    horizon: int = param(10, 'T of the rollout loss on D_test, samples', ge=1)
    lr: float = param(3e-3, 'Adam step size of meta-training', gt=0)
    gamma: float = param(1e-5, 'proximal strength of the closed-form head fit towards the '
                               "meta-model's head, meta-training's inner solve and "
                               'adaptation (mean-loss units)', ge=0)
    seed: int = 0

    def validate(self) -> None:
        if self.method not in NARX_METHODS:
            raise ValueError(f'method must be one of {NARX_METHODS}, got {self.method!r}')
        for name in ('iterations', 'batch_size', 'windows', 'horizon'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name} must be >= 1, got {getattr(self, name)}')
        if not (self.lr > 0 and self.gamma >= 0):
            raise ValueError(f'need lr > 0 and gamma >= 0, got {self.lr}, {self.gamma}')


@dataclass
class MetaResult:
    """Meta-trained parameters and the outer loss of every outer step (normalised units:
    iMAML's D_test rollout loss, MAML's projected loss)."""

    params: Params
    curve: List[float] = field(default_factory=list)
    elapsed: float = 0.0


def _split(records: Sequence[Record], share: float) -> Tuple[List[Record], List[Record]]:
    """Each record's first 1 - share and its last share, in time (meta-training: D_tr and
    D_test, share 1/2, as SourceSet; adaptation: its validation)."""
    first, last = [], []
    for u, y in records:
        cut = len(y) - int(round(len(y) * share))
        first.append((u[:cut], y[:cut]))
        last.append((u[cut:], y[cut:]))
    return first, last


def _windows(shape: NarxShape, norm: Normalisation, records: Sequence[Record], horizon: int):
    parts = [state_windows(shape, *norm.normalise(u, y), horizon) for u, y in records]
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))


def outer_loss(shape: NarxShape, params: Params, train: Tuple[torch.Tensor, ...],
               test: Tuple[torch.Tensor, ...], config: NarxMetaConfig) -> torch.Tensor:
    """One outer step's loss (`train` = (s (B, W, n_s), u (B, W, 1, n_u), y (B, W, 1, n_y))
    D_tr's one-step windows, `test` D_test's T-step windows, T its second-last size).

    'imaml', eq. (outer): each task's head solved on D_tr at gamma, the mean T-step rollout
    loss on D_test, autograd through the solve (the exact implicit meta-gradient).
    'maml', first order by variable projection (Golub & Pereyra; ANIL's head-only
    adaptation): each task's head solved at gamma on all its one-step equations (D_tr's and
    the first step of D_test's windows), the loss the inner objective itself, one-step loss +
    gamma/2 ||Theta* - Theta_bar||^2, at that head held fixed (no gradient through the
    solve). Since Theta* minimises that objective, its partial derivatives at the held head
    are the total ones (the envelope theorem): the first-order gradient is exact here.
    """
    (s_tr, u_tr, y_tr), (s_te, u_te, y_te) = train, test
    if config.method == 'maml':
        return projected_loss(shape, params, torch.cat([s_tr, s_te], 1),
                              torch.cat([u_tr[..., 0, :], u_te[..., 0, :]], 1),
                              torch.cat([y_tr[..., 0, :], y_te[..., 0, :]], 1), config.gamma)
    phi = regressors(shape, params, s_tr, u_tr[..., 0, :])
    head = ridge(phi, y_tr[..., 0, :], params['head'], config.gamma)
    y_hat = rollout(shape, params, s_te, u_te, head[:, None])
    return (y_hat - y_te).square().sum(-1).mean()


def projected_loss(shape: NarxShape, params: Params, s: torch.Tensor, u_next: torch.Tensor,
                   y_next: torch.Tensor, gamma: float) -> torch.Tensor:
    """The variable-projection loss of :func:`outer_loss`'s 'maml', averaged over tasks:
    s (B, M, n_s), u_next (B, M, n_u), y_next (B, M, n_y) one-step equations; the head
    solved without a graph, the gradient the partial one at it (exact, the envelope theorem;
    to the ridge's relative floor RIDGE_FLOOR where gamma / 2 is below it).
    """
    phi = regressors(shape, params, s, u_next)
    prior = params['head']
    with torch.no_grad():
        head = ridge(phi, y_next, prior, gamma)
    return (mean_loss(phi, y_next, head)
            + gamma / 2 * (head - prior).square().sum((-1, -2))).mean()


def meta_train(shape: NarxShape, norm: Normalisation, systems: Sequence[Sequence[Record]],
               config: NarxMetaConfig, progress: Optional[Callable[[int, float], None]] = None
               ) -> MetaResult:
    """Meta-train g and the prior head on source `systems` (each a list of trajectories).

    Raises:
        ValueError: a bad config, or a system too short for one window in each half.
    """
    config.validate()
    rng = np.random.default_rng(config.seed)
    tasks = []
    for i, records in enumerate(systems):
        tr, te = _split(records, 0.5)
        w_tr, w_te = _windows(shape, norm, tr, 1), _windows(shape, norm, te, config.horizon)
        if len(w_tr[0]) == 0 or len(w_te[0]) == 0:
            raise ValueError(f'source system {i} is too short for a window in each half')
        tasks.append((w_tr, w_te))
    params = {k: v.requires_grad_() for k, v in init_params(shape, config.seed).items()}
    opt = torch.optim.Adam(list(params.values()), lr=config.lr)
    result = MetaResult(params={})
    start = time.monotonic()
    for it in range(config.iterations):
        batch = rng.choice(len(tasks), size=min(config.batch_size, len(tasks)), replace=False)
        pick = [(w, rng.integers(len(w[0]), size=config.windows)) for t in batch
                for w in tasks[t]]
        s_tr, u_tr, y_tr = (torch.from_numpy(np.stack([w[j][idx] for w, idx in pick[0::2]]))
                            for j in range(3))
        s_te, u_te, y_te = (torch.from_numpy(np.stack([w[j][idx] for w, idx in pick[1::2]]))
                            for j in range(3))
        loss = outer_loss(shape, params, (s_tr, u_tr, y_tr), (s_te, u_te, y_te), config)
        if not torch.isfinite(loss):
            raise ValueError(f'meta-training loss turned non-finite at step {it}')
        opt.zero_grad()
        loss.backward()
        opt.step()
        result.curve.append(float(loss.detach()))
        if progress is not None:
            progress(it + 1, result.curve[-1])
    result.params = {k: v.detach().clone() for k, v in params.items()}
    result.elapsed = time.monotonic() - start
    return result


@dataclass
class AdaptedNarx:
    """An adapted feature NARX and how its head was found.

    Attributes:
        model: the adapted model.
        train_loss: its one-step loss on the training samples (normalised units).
        arx_loss: the least-squares ARX(p)'s on the same samples.
        rule: 'ridge' (toward the meta-model), 'ridge_to_arx' (toward the ARX's head: the
            fit toward the meta-model lost to the ARX), 'arx' (the ARX's own head, where
            rounding left even that above) or 'arx_validated' (the ARX's head: the fit lost to
            it on the held-back part of the samples, :func:`adapt`).
    """

    model: FeatureNarx
    train_loss: float
    arx_loss: float
    rule: str


def one_step_data(shape: NarxShape, params: Params, norm: Normalisation,
                  records: Sequence[Record]) -> Tuple[torch.Tensor, torch.Tensor]:
    """(phi (M, n_phi), y_{t+1} (M, n_y)) of every one-step equation in `records`."""
    s, u, y = (torch.from_numpy(a) for a in _windows(shape, norm, records, 1))
    with torch.no_grad():
        return regressors(shape, params, s, u[:, 0]), y[:, 0]


def _arx_head(shape: NarxShape, phi: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The least-squares ARX(p) head on the one-step equations: g's columns left out (zero)."""
    lin = torch.ones(shape.n_phi, dtype=torch.bool)
    lin[shape.n_s:shape.n_s + shape.features] = False
    head = torch.zeros((shape.n_y, shape.n_phi), dtype=phi.dtype)
    head[:, lin] = ridge(phi[:, lin], y, head[:, lin], 0.0)
    return head


def _data(meta: FeatureNarx, records: Sequence[Record]) -> Tuple[torch.Tensor, torch.Tensor]:
    phi, y = one_step_data(meta.shape, meta.params, meta.norm, records)
    if len(y) == 0:
        raise ValueError(f'no target samples: ARX({meta.shape.order}) needs records longer '
                         f'than {meta.shape.order}')
    return phi, y


def arx_model(meta: FeatureNarx, records: Sequence[Record]) -> FeatureNarx:
    """The least-squares ARX(p) of `records` as a feature NARX (its feature columns zero):
    the linear baseline of the same samples. ValueError: no one-step equation."""
    phi, y = _data(meta, records)
    return FeatureNarx(meta.shape, meta.norm, {**meta.params,
                                               'head': _arx_head(meta.shape, phi, y)})


def _fit(meta: FeatureNarx, phi: torch.Tensor, y: torch.Tensor, gamma: float,
         toward_arx: bool = True) -> Tuple[torch.Tensor, str, float, torch.Tensor, float]:
    """(head, rule, its loss, the ARX's head, its loss) on the one-step equations (phi, y):
    the ridge fit toward the meta-model; where that loses to the ARX, the fit toward the ARX's
    head (`toward_arx`) or the ARX's head itself (rule 'arx')."""
    arx_head = _arx_head(meta.shape, phi, y)
    arx_loss = float(mean_loss(phi, y, arx_head))
    head, rule = ridge(phi, y, meta.params['head'], gamma), 'ridge'
    loss = float(mean_loss(phi, y, head))
    if loss > arx_loss and not toward_arx:
        return arx_head, 'arx', arx_loss, arx_head, arx_loss
    if loss > arx_loss:
        # Toward the ARX's head instead: the minimum of loss + gamma/2 ||Theta - Theta_arx||^2
        # is at most the ARX's loss (Theta_arx is a candidate), and gamma keeps it
        # regularised where the features are collinear with the lags (plain least squares
        # there gave heads that cancel on the samples and not off them).
        head, rule = ridge(phi, y, arx_head, gamma), 'ridge_to_arx'
        loss = float(mean_loss(phi, y, head))
    if not (loss <= arx_loss) or not math.isfinite(loss):
        head, rule, loss = arx_head, 'arx', arx_loss
    return head, rule, loss, arx_head, arx_loss


def adapt(meta: FeatureNarx, records: Sequence[Record], gamma: float,
          toward_arx: bool = True) -> AdaptedNarx:
    """Algorithm 2 for the feature NARX (module docstring) on the target `records`.
    `toward_arx` False: where the fit toward the meta-model loses to the ARX on the samples,
    the ARX's head flies (rule 'arx') instead of a fit toward it with the features free.

    Then the validation in time: both fits (this rule and the ARX's) again on each record's
    first VALIDATION_SHARE-complement, their VALIDATION_HORIZON-step rollout loss on its last
    VALIDATION_SHARE; where the feature NARX's is the higher, the ARX's head (of all samples)
    flies, rule 'arx_validated': a fit that wins on its own samples and loses off them (the
    features extrapolating) is not flown. Skipped where the last part holds no window.

    Raises:
        ValueError: no one-step equation in the records.
    """
    phi, y = _data(meta, records)
    head, rule, loss, arx_head, arx_loss = _fit(meta, phi, y, gamma, toward_arx)
    fit_part, check_part = _split(records, VALIDATION_SHARE)
    windows = _windows(meta.shape, meta.norm, check_part, VALIDATION_HORIZON)
    if rule != 'arx' and len(windows[0]) and len(_data(meta, fit_part)[1]):
        part_head, _, _, part_arx, _ = _fit(meta, *_data(meta, fit_part), gamma, toward_arx)
        s, u, y_check = (torch.from_numpy(a) for a in windows)
        with torch.no_grad():
            own, arx = ((rollout(meta.shape, meta.params, s, u, h) - y_check)
                        .square().sum(-1).mean() for h in (part_head, part_arx))
        if float(own) > float(arx):
            head, rule, loss = arx_head, 'arx_validated', arx_loss
    params = {**{k: v.clone() for k, v in meta.params.items()}, 'head': head}
    return AdaptedNarx(FeatureNarx(meta.shape, meta.norm, params), loss, arx_loss, rule)


def one_step_loss(model: FeatureNarx, records: Sequence[Record]) -> float:
    """The mean one-step loss of `model` on every one-step equation in `records` (normalised
    units): the training loss :func:`adapt` reports. ValueError: no one-step equation."""
    phi, y = _data(model, records)
    return float(mean_loss(phi, y, model.params['head']))


def heldout_loss(model: FeatureNarx, records: Sequence[Record], horizon: int) -> float:
    """Mean T-step rollout loss (summed over outputs) on every window of `records`,
    normalised units: the l_SSM of eq. (SSM) for this model."""
    windows = _windows(model.shape, model.norm, records, horizon)
    s, u, y = (torch.from_numpy(a) for a in windows)
    with torch.no_grad():
        return float((rollout(model.shape, model.params, s, u) - y).square().sum(-1).mean())


__all__ = ['NARX_METHODS', 'NarxMetaConfig', 'MetaResult', 'AdaptedNarx', 'outer_loss',
           'projected_loss', 'meta_train', 'adapt', 'arx_model', 'heldout_loss', 'one_step_data',
           'one_step_loss']
