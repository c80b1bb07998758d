"""The check a new model must pass before the controller flies it: a score, no rule of when.

Scores the N-step prediction of the plant under the inputs really applied, on samples of the
episode (u (K, n_u), y (K, n_y)): from every ``stride``-th start t, z_t by eq. (z) from H
samples, y_hat by eqs. (z_next), (haty) under u_{t+1..t+N} (N: the planner's horizon);
E = mean ((y - y_hat) / s_i)^2, s_i the std of output i. It passes when E_candidate <=
(1 + margin) E_reference: the model in use when the candidate updates it, else persistence
(y_hat = y_t). Too few samples: unchecked. Which samples, which models and when: the gate
(:mod:`~metampc_controller.model_gate`). Pure numpy (no rclpy); why and what it refused:
docs/mpc.md#the-check-before-a-model-flies.
"""
from dataclasses import dataclass
import math
from typing import Optional

import numpy as np

from metampc_common.params import param
from metampc_controller.mpc import MpcConfig
from metampc_controller.offset_free import DisturbanceEstimator
from metampc_model.predictor import NssmPredictor


@dataclass
class ModelCheckConfig:
    """How the check scores (node parameters, live)."""

    model_check_margin: float = param(0.0, 'a new model flies if its error is at most (1 + '
                                           'margin) times the yardstick\'s: > 0 lets a '
                                           'slightly worse one fly, < 0 asks for a clear gain',
                                      gt=-1, live=True)
    model_check_window: int = param(200, 'latest samples of the episode the check scores at a '
                                         'model\'s arrival', ge=1, le=900, live=True)
    model_check_stride: int = param(5, 'samples between the starts of the scored predictions',
                                    ge=1, live=True)
    model_check_as_planned: bool = param(False, 'score each model as the MPC plans with it: '
                                                'corrected by its own offset-free disturbance '
                                                'estimate (when offset_free is on)', live=True)


@dataclass(frozen=True)
class Verdict:
    """The check's answer, in fields (:meth:`reason` words them).

    Attributes:
        ok: the candidate may fly.
        candidate, reference: E of the candidate and of the yardstick (nan when unchecked).
        scored: samples scored (0: unchecked: `held` in the episode, `needed` to check).
        held, needed: see `scored`.
        persistence: the yardstick is persistence (no model of the candidate's method).
        score: what E is ('20-step prediction error', '... (offset-free state, as planned)').
        limit: 1 + ``model_check_margin``: E_candidate may be at most limit x E_reference.
        error: why the candidate cannot be scored (its disturbance is not detectable), or ''.
    """

    ok: bool
    candidate: float = math.nan
    reference: float = math.nan
    scored: int = 0
    held: int = 0
    needed: int = 0
    persistence: bool = False
    score: str = ''
    limit: float = 1.0
    error: str = ''

    def reason(self, where: str = 'the latest of the episode',
               yardstick: str = 'the model in use') -> str:
        """One line: why it may not fly, or what was compared; `where` names the scored
        samples, `yardstick` the model compared against (persistence says itself)."""
        if self.error:
            return f'check: {self.error}'
        if not self.scored:
            return (f'unchecked: {self.held} samples in the episode, the check needs '
                    f'{self.needed}')
        what = 'persistence (y stays)' if self.persistence else yardstick
        if not self.ok:
            return (f'check: its {self.score} {self.candidate:.4g} on {self.scored} samples '
                    f'({where}) exceeds {self.limit:g} x {self.reference:.4g} of {what}')
        return (f'check passed: {self.score} {self.candidate:.4g} on {self.scored} samples '
                f'({where}) against {self.reference:.4g} of {what}')


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


def _corrected(model: NssmPredictor, u: np.ndarray, y: np.ndarray, first: int,
               mpc: MpcConfig):
    """The prediction the MPC plans with when offset-free: the model's disturbance estimate p_t
    (the MPC's estimator, run over every sample from the H-th on) shifts its constants e, d
    for the N steps after t. Raises ValueError (the rank test) for a model whose disturbance
    is not detectable."""
    latent, h, horizon = model.latent, model.config.history, mpc.horizon
    est = DisturbanceEstimator.of(latent, mpc.offset_free, mpc.disturbance_gain)
    n_z, const, start = latent.n_z, np.empty(latent.n_z + latent.n_y), {}
    for t in range(h - 1, len(y) - horizon):
        z = model.encode(u[t - h + 1:t + 1], y[t - h + 1:t + 1])
        est.update(z, u[t], y[t])
        if t >= first:
            start[t] = (z, est.constants(const).copy())

    def predict(t: int) -> np.ndarray:
        z, c = start[t]
        return latent.rollout(z, u[t + 1:t + 1 + horizon], c[:n_z], c[n_z:])
    return predict


def check(candidate: NssmPredictor, current: Optional[NssmPredictor], u: np.ndarray,
          y: np.ndarray, mpc: MpcConfig, config: ModelCheckConfig,
          scored: Optional[int] = None) -> Verdict:
    """Verdict on `candidate` against `current` (None: persistence) on the last `scored`
    samples (default ``model_check_window``) of the episode's u (K, n_u), y (K, n_y), the H
    before them as history (module docstring), predicting N = the planner's (`mpc`) horizon
    steps. With ``model_check_as_planned`` and the planner's offset-free form each model is
    scored as the MPC plans with it: corrected by its own disturbance estimate (the planner's
    gain), run from up to :func:`warmup` samples before the scored ones. Which models to
    check, and when, is the gate's (:mod:`model_gate`)."""
    horizon = mpc.horizon
    h = max(candidate.config.history, current.config.history if current is not None else 1)
    scored = config.model_check_window if scored is None else scored
    if min(len(y), scored + h) < h + horizon + 1:
        return Verdict(True, held=min(len(y), scored + h), needed=h + horizon + 1)
    corrected = config.model_check_as_planned and mpc.offset_free != 'none'
    rows = scored + h + (warmup(mpc.disturbance_gain) if corrected else 0)
    u, y = u[-rows:], y[-rows:]
    first = max(h, len(y) - scored) - 1      # y_{first+1} is the first scored sample
    scale = np.std(y[first + 1 - h:], axis=0)      # the scored samples and their history
    scale = np.where(scale > 1e-9, scale, 1.0)

    def scorer(model: Optional[NssmPredictor]):
        if model is None:
            return _persistence(y, horizon)
        if corrected:
            return _corrected(model, u, y, first, mpc)
        return _plain(model, u, y, horizon)
    args = (y, first, horizon, config.model_check_stride, scale)
    try:
        new = n_step_error(scorer(candidate), *args)
    except ValueError as err:          # its disturbance is not detectable: it cannot fly
        return Verdict(False, error=str(err))
    ref = n_step_error(scorer(current), *args)
    limit = 1.0 + config.model_check_margin
    return Verdict(math.isfinite(new) and not new > limit * ref, new, ref, len(y) - first - 1,
                   persistence=current is None, limit=limit,
                   score=f'{horizon}-step prediction error' + (
                       f' (offset-free {mpc.offset_free}, as planned)' if corrected else ''))
