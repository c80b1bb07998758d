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
    model_check_stride: int = param(5, 'samples between the starts of the scored predictions',
                                    ge=1, live=True)


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


def n_step_error(predict, u: np.ndarray, y: np.ndarray, history: int, horizon: int,
                 stride: int, scale: np.ndarray) -> float:
    """E of a predictor over the samples (u (K, n_u), y (K, n_y); row k of u produced row k
    of y): predict(u_hist (H, n_u), y_hist (H, n_y), u_future (N, n_u)) -> (N, n_y)."""
    total, count = 0.0, 0
    for t in range(history - 1, len(y) - horizon, stride):
        lo = t - history + 1
        pred = predict(u[lo:t + 1], y[lo:t + 1], u[t + 1:t + 1 + horizon])
        err = (y[t + 1:t + 1 + horizon] - pred) / scale
        total += float(np.sum(err * err))
        count += err.size
    return total / count if count else math.nan


def _own_history(model: NssmPredictor):
    """The model's predict, given the latest of (possibly more) history rows."""
    h = model.config.history
    return lambda u_hist, y_hist, u_future: model.predict(u_hist[-h:], y_hist[-h:], u_future)


def _persistence(u_hist: np.ndarray, y_hist: np.ndarray, u_future: np.ndarray) -> np.ndarray:
    return np.repeat(y_hist[-1:], len(u_future), axis=0)


def check(candidate: NssmPredictor, current: Optional[NssmPredictor], u: np.ndarray,
          y: np.ndarray, horizon: int, config: ModelCheckConfig, scored: Optional[int] = None,
          where: str = 'the latest of the episode') -> Verdict:
    """Verdict on `candidate` against `current` (None: persistence) on the last `scored`
    samples (default ``model_check_window``) of the episode's u (K, n_u), y (K, n_y), the H
    before them as history (module docstring); `where` names them in the reason. Which
    models to check is the caller's (:func:`applies`)."""
    h = max(candidate.config.history, current.config.history if current is not None else 1)
    scored = config.model_check_window if scored is None else scored
    u, y = u[-(scored + h):], y[-(scored + h):]
    if len(y) < h + horizon + 1:
        return Verdict(True, f'unchecked: {len(y)} samples in the episode, the check needs '
                             f'{h + horizon + 1}')
    scale = np.std(y, axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    args = (u, y, h, horizon, config.model_check_stride, scale)
    new = n_step_error(_own_history(candidate), *args)
    ref = n_step_error(_own_history(current) if current is not None else _persistence, *args)
    what = 'the model in use' if current is not None else 'persistence (y stays)'
    limit = (1.0 + config.model_check_margin) * ref
    if not math.isfinite(new) or new > limit:
        margin = config.model_check_margin
        return Verdict(False, f'check: its {horizon}-step prediction error {new:.4g} on '
                              f'{len(y) - h} samples ({where}) exceeds {1 + margin:g} x '
                              f'{ref:.4g} of {what}', new, ref)
    return Verdict(True, f'check passed: {horizon}-step prediction error {new:.4g} on '
                         f'{len(y) - h} samples ({where}) against {ref:.4g} of {what}', new,
                   ref)
