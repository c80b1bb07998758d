"""The check a new model must pass before the controller flies it.

Scores the N-step prediction of the plant under the inputs really applied, on samples of the
episode (u (K, n_u), y (K, n_y)): from every ``stride``-th start t, z_t by eq. (z) from H
samples, y_hat by eqs. (z_next), (haty) under u_{t+1..t+N}; E = mean ((y - y_hat) / s_i)^2,
s_i the std of output i. It passes when E_candidate <= (1 + margin) E_reference: the model in
use when the candidate updates it, else persistence (y_hat = y_t). An answer to the pending
adaptation request is scored on the ``model_check_trial`` samples after its swap step (unseen
by its adaptation; the model in use controls meanwhile), any other model at arrival on the
latest ``model_check_window``. Too few samples: unchecked. Pure numpy (no rclpy); why and what
it refused: docs/mpc.md#the-check-before-a-model-flies.
"""
from dataclasses import dataclass
import math
from typing import Optional

import numpy as np

from metampc_common.params import param
from metampc_controller.offset_free import DisturbanceEstimator, disturbance_model
from metampc_model.predictor import NssmPredictor

CHECKED = ('requested', 'all', 'off')


@dataclass
class ModelCheckConfig:
    """Settings of the check (node parameters, live)."""

    model_check: str = param('requested', 'which new models must pass the check before they '
                                          'fly: requested (answers to adaptation requests, '
                                          'late ones too), all, off', choices=CHECKED,
                             live=True)
    model_check_margin: float = param(0.0, 'a new model flies if its error is at most (1 + '
                                           'margin) times the yardstick\'s: > 0 lets a '
                                           'slightly worse one fly, < 0 asks for a clear gain',
                                      gt=-1, live=True)
    model_check_window: int = param(200, 'latest samples of the episode the check scores at a '
                                         'model\'s arrival', ge=1, le=900, live=True)
    model_check_trial: int = param(50, 'samples an answer to an adaptation request is tried on '
                                       'before it flies, the model in use going on meanwhile '
                                       '(scored on them alone: its adaptation never saw them); '
                                       '0: checked at arrival like any model; else at least '
                                       'the horizon', ge=0, le=900, live=True)
    model_check_probation: int = param(0, 'samples a requested model that flew is judged on, '
                                          'on its own loop, against the model it replaced, '
                                          'which comes back if it predicts them better; 0: '
                                          'none; else at least the horizon', ge=0, le=900,
                                       live=True)
    model_check_stride: int = param(5, 'samples between the starts of the scored predictions',
                                    ge=1, live=True)
    model_check_as_planned: bool = param(False, 'score each model as the MPC plans with it: '
                                                'corrected by its own offset-free disturbance '
                                                'estimate (when offset_free is on)', live=True)


@dataclass
class Verdict:
    """The check's answer.

    Attributes:
        ok: the candidate may fly.
        reason: one line: why it may not, or what was compared ('unchecked: ...' without data).
        candidate, reference: E of the candidate and of the yardstick (nan when unchecked).
    """

    ok: bool
    reason: str
    candidate: float = math.nan
    reference: float = math.nan


def applies(config: ModelCheckConfig, requested: bool) -> bool:
    """Whether a new model is checked: `requested` if it answers an adaptation request."""
    return config.model_check == 'all' or (config.model_check == 'requested' and requested)


def n_step_error(predict, y: np.ndarray, first: int, horizon: int, stride: int,
                 scale: np.ndarray) -> float:
    """E over the starts t = first, first + stride, ... with t + N < K of y (K, n_y):
    predict(t) -> (N, n_y) the prediction of y_{t+1..t+N} made at t."""
    total, count = 0.0, 0
    for t in range(first, len(y) - horizon, stride):
        err = (y[t + 1:t + 1 + horizon] - predict(t)) / scale
        total += float(np.sum(err * err))
        count += err.size
    return total / count if count else math.nan


def _plain(model: NssmPredictor, u: np.ndarray, y: np.ndarray, horizon: int):
    """The model's prediction from its own H latest rows, under the inputs really applied."""
    h = model.config.history
    return lambda t: model.predict(u[t - h + 1:t + 1], y[t - h + 1:t + 1],
                                   u[t + 1:t + 1 + horizon])


def _persistence(y: np.ndarray, horizon: int):
    return lambda t: np.repeat(y[t:t + 1], horizon, axis=0)


def warmup(gain: float) -> int:
    """Samples after which the offset-free estimate has forgotten its start to 1e-3:
    the least W with (1 - g)^W <= 1e-3 (10 at the default g = 0.5)."""
    return 1 if gain >= 1.0 else math.ceil(math.log(1e-3) / math.log(1.0 - gain))


def _corrected(model: NssmPredictor, u: np.ndarray, y: np.ndarray, horizon: int, first: int,
               form: str, gain: float):
    """The prediction the MPC plans with when offset-free: the model's disturbance estimate p_t
    (offset_free.DisturbanceEstimator run over every sample from the H-th on) shifts its
    constants e, d for the N steps after t. Raises ValueError (the rank test) for a model
    whose disturbance is not detectable."""
    latent, h = model.latent, model.config.history
    est = DisturbanceEstimator(latent, disturbance_model(latent, form), gain)
    n_z, const, start = latent.n_z, np.empty(latent.n_z + latent.n_y), {}
    for t in range(h - 1, len(y) - horizon):
        z = model.encode(u[t - h + 1:t + 1], y[t - h + 1:t + 1])
        est.update(z, u[t], y[t])
        if t >= first:
            start[t] = (z, est.constants(const).copy())

    def predict(t: int) -> np.ndarray:
        z, c = start[t]
        out = np.empty((horizon, latent.n_y))
        for k in range(horizon):
            z = latent.A @ z + latent.B @ u[t + 1 + k] + c[:n_z]
            out[k] = latent.C @ z + c[n_z:]
        return out
    return predict


def check(candidate: NssmPredictor, current: Optional[NssmPredictor], u: np.ndarray,
          y: np.ndarray, horizon: int, config: ModelCheckConfig, scored: Optional[int] = None,
          where: str = 'the latest of the episode', offset_free: str = 'none',
          disturbance_gain: float = 0.5, current_name: str = 'the model in use') -> Verdict:
    """Verdict on `candidate` against `current` (None: persistence) on the last `scored`
    samples (default ``model_check_window``) of the episode's u (K, n_u), y (K, n_y), the H
    before them as history (module docstring); `where` names them in the reason. With an
    `offset_free` form each model is scored as the MPC plans with it: corrected by its own
    disturbance estimate (gain `disturbance_gain`), run from up to :func:`warmup` samples
    before the scored ones; `current_name` names `current` in the reason. Which models to
    check is the caller's (:func:`applies`)."""
    h = max(candidate.config.history, current.config.history if current is not None else 1)
    scored = config.model_check_window if scored is None else scored
    if min(len(y), scored + h) < h + horizon + 1:
        return Verdict(True, f'unchecked: {min(len(y), scored + h)} samples in the episode, '
                             f'the check needs {h + horizon + 1}')
    corrected = offset_free != 'none'
    rows = scored + h + (warmup(disturbance_gain) if corrected else 0)
    u, y = u[-rows:], y[-rows:]
    first = max(h, len(y) - scored) - 1      # y_{first+1} is the first scored sample
    scale = np.std(y[first + 1 - h:], axis=0)      # the scored samples and their history
    scale = np.where(scale > 1e-9, scale, 1.0)

    def scorer(model: Optional[NssmPredictor]):
        if model is None:
            return _persistence(y, horizon)
        if corrected:
            return _corrected(model, u, y, horizon, first, offset_free, disturbance_gain)
        return _plain(model, u, y, horizon)
    args = (y, first, horizon, config.model_check_stride, scale)
    try:
        new = n_step_error(scorer(candidate), *args)
    except ValueError as err:          # its disturbance is not detectable: it cannot fly
        return Verdict(False, f'check: {err}')
    ref = n_step_error(scorer(current), *args)
    what = current_name if current is not None else 'persistence (y stays)'
    kind = f'{horizon}-step prediction error' + (
        f' (offset-free {offset_free}, as planned)' if corrected else '')
    n = len(y) - first - 1
    limit = (1.0 + config.model_check_margin) * ref
    if not math.isfinite(new) or new > limit:
        margin = config.model_check_margin
        return Verdict(False, f'check: its {kind} {new:.4g} on {n} samples ({where}) exceeds '
                              f'{1 + margin:g} x {ref:.4g} of {what}', new, ref)
    return Verdict(True, f'check passed: {kind} {new:.4g} on {n} samples ({where}) against '
                         f'{ref:.4g} of {what}', new, ref)
