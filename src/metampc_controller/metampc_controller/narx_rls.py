"""The feature NARX's head adapted at every tick by recursive least squares, in the loop.

At the tick of step k the sample (phi(s_{k-1}, u_k), y_k) updates the head columns `rls_columns`
of the model in use (:class:`~metampc_model.head_rls.HeadRls`, normalised units; prior: the head
the model came with, precision r0 = rls_prior_gamma / (2 (1 - lam)): the learner's ridge over the
forgetting's window; g stays). Not taken, counted: a non-finite sample, a saturated u_k (at the
input bounds), a step whose linearisation at (s_k, u_k) leaves the family :func:`accepted`
describes. A new episode or model starts from the prior. :meth:`NarxRls.tick` returns the
a-priori one-step std of y_k per output (physical; ``MpcStatus.one_step_std``) and keeps the
normalised innovation (the a-priori error over that std, the posterior trigger's input; NaN
until 1 / (1 - lam) samples were taken since the prior: the noise estimate's memory). Numpy
only; measured: docs/adaptation.md#recursive-least-squares-on-the-feature-narx.
"""
from dataclasses import dataclass
from typing import Optional

import numpy as np

from metampc_common.params import param
from metampc_model.head_rls import HeadRls
from metampc_model.narx_predictor import NarxPredictor

RLS_COLUMNS = ('all', 'linear', 'bias')
# An input within this of a bound counts as saturated (the bounds' own units).
SATURATION_TOL = 1e-9


@dataclass
class RlsConfig:
    """Settings of the in-loop RLS (controller node parameters, read at start-up)."""

    rls_forgetting: float = param(0.0, 'a feature NARX: its head adapted at every tick by '
                                       'recursive least squares with this forgetting factor '
                                       '(0: off)', ge=0, lt=1)
    rls_prior_gamma: float = param(10.0, 'the in-loop RLS: strength of its prior (the head the '
                                         'model came with) in the learner\'s mean-loss units '
                                         '(narx_gamma\'s role) over the forgetting\'s window',
                                   gt=0)
    rls_columns: str = param('all', 'the in-loop RLS: the head columns it adapts (all; linear: '
                                    'lags, input and constant; bias: the constant)',
                             choices=RLS_COLUMNS)


def accepted(predictor: NarxPredictor, head: np.ndarray, prior: np.ndarray, s: np.ndarray,
             u: np.ndarray) -> bool:
    """Whether `head` stays in the family of models the loop flies, at the operating point
    (s, u) (physical): its linearisation is finite, its spectral radius at most max(1, the
    prior's there), and its input acts with the prior's sign (sum of D_u * D_u,prior > 0,
    D_u = dy_{t+1}/du_{t+1})."""
    try:
        new, old = predictor.linearise(s, u, head), predictor.linearise(s, u, prior)
    except ValueError:
        return False
    n_y = predictor.shape.n_y
    rho = np.max(np.abs(np.linalg.eigvals(new.A)))
    bound = max(1.0, np.max(np.abs(np.linalg.eigvals(old.A))))
    return bool(rho <= bound and np.sum(new.B[:n_y] * old.B[:n_y]) > 0)


@dataclass
class RlsCounts:
    """Samples of the model in use: taken, refused (would leave the family), saturated and
    non-finite (left out), resets (R not positive definite: the prior again)."""

    taken: int = 0
    refused: int = 0
    saturated: int = 0
    nonfinite: int = 0
    resets: int = 0


class NarxRls:
    """The module docstring's loop for the controller core: one :meth:`tick` per tick."""

    def __init__(self, config: RlsConfig):
        lam = config.rls_forgetting
        if not (0 < lam < 1 and config.rls_prior_gamma > 0):
            raise ValueError(f'rls_forgetting must lie in (0, 1) and rls_prior_gamma be > 0, '
                             f'got {lam}, {config.rls_prior_gamma}')
        self.config = config
        self.precision = config.rls_prior_gamma / 2 / (1 - lam)
        self.memory = int(round(1 / (1 - lam)))     # samples before an innovation is kept
        self.counts = RlsCounts()
        self.event = ''       # what the latest tick did that a log should say ('' nothing)
        # the latest tick's (y_k - y_hat_k) / std per output, before y_k was taken (NaN: none)
        self.innovation = np.zeros(0)
        self._predictor: Optional[NarxPredictor] = None
        self._rls: Optional[HeadRls] = None
        self._prior = np.zeros((0, 0))
        self._cols = np.zeros(0, bool)
        self._last: Optional[tuple] = None    # (step, s) of the previous tick

    def _bind(self, predictor: NarxPredictor) -> None:
        """Adapt `predictor`'s head from now on, its head as it comes the prior."""
        sh = predictor.shape
        self._predictor, self.counts = predictor, RlsCounts()
        self._prior = np.array(predictor.head)
        self._cols = np.ones(sh.n_phi, bool)
        if self.config.rls_columns == 'linear':
            self._cols[sh.n_s:sh.n_s + sh.features] = False
        elif self.config.rls_columns == 'bias':
            self._cols[:-1] = False
        self._rls = HeadRls(self._prior[:, self._cols], self.precision,
                            self.config.rls_forgetting)
        self._last = None

    def _full(self, columns: np.ndarray) -> np.ndarray:
        """The whole head with `columns` in the adapted columns, the prior's elsewhere."""
        full = self._prior.copy()
        full[:, self._cols] = columns
        return full

    def tick(self, predictor: NarxPredictor, step: int, s: np.ndarray, u: np.ndarray,
             y: np.ndarray, u_min: np.ndarray, u_max: np.ndarray) -> np.ndarray:
        """Take sample (phi(s_{k-1}, u_k), y_k) of step k = `step` into `predictor`'s head
        (s: s_k; u: u_k; y: y_k; bounds of u); returns the std of y_k's one-step prediction
        before it (n_y,), NaN where there is none (the first two samples of an episode or model:
        no prediction, then no noise estimate yet)."""
        self.event = ''
        if predictor is not self._predictor:
            self._bind(predictor)
        rls, last, nm, cols = self._rls, self._last, predictor.norm, self._cols
        self._last = (step, np.array(s, dtype=np.float64))
        self.innovation = np.full(predictor.shape.n_y, np.nan)
        if last is None or last[0] != step - 1:     # a new episode: from the prior
            rls.reset()
            predictor.set_head(self._prior)
            return np.full(predictor.shape.n_y, np.nan)
        phi_all = predictor.regressors(last[1], u)
        phi = phi_all[cols]
        # the part of y_k the fixed columns explain is the prior's
        y_n = ((np.asarray(y, np.float64) - nm.y_mean) / nm.y_std
               - self._prior[:, ~cols] @ phi_all[~cols])
        finite = bool(np.all(np.isfinite(phi_all)) and np.all(np.isfinite(y_n)))
        if not finite:
            self.counts.nonfinite += 1
            return np.full(len(y_n), np.nan)
        std_n = rls.predictive_std(phi)
        if rls.since_prior >= self.memory:
            self.innovation = (y_n - rls.head @ phi) / std_n
        std = std_n * nm.y_std
        if np.any(u <= u_min + SATURATION_TOL) or np.any(u >= u_max - SATURATION_TOL):
            self.counts.saturated += 1
            return std
        candidate = rls.candidate(phi, y_n)
        if candidate is not None and not accepted(predictor, self._full(candidate[0]),
                                                  self._prior, s, u):
            self.counts.refused += 1
            return std
        if rls.take(phi, y_n, candidate) == 'reset':
            self.counts.resets += 1
            self.event = (f'rls: the information matrix lost positive definiteness at step '
                          f'{step}; the head is reset to the prior')
        else:
            self.counts.taken += 1
        predictor.set_head(self._full(rls.head))
        return std


__all__ = ['RLS_COLUMNS', 'SATURATION_TOL', 'RlsConfig', 'RlsCounts', 'NarxRls', 'accepted']
