"""The feature NARX's head refined on its free-run simulation error (output error).

The closed-form head (:mod:`.closed_form`) minimises the one-step (equation) error; fed its own
outputs over a long record a model so fitted drifts, and with noise on the measured outputs the
equation error is biased where the simulation error is not (Ljung, System Identification, ch. 7).
Here the head Theta (g fixed) takes Levenberg-Marquardt steps from a given head on

    L(Theta) = 1/K sum_records sum_{t >= p} ||y_t - y_sim_t(Theta)||^2     (normalised units)

y_sim the model's free run from each record's first p samples, its Jacobian by forward
sensitivities along the run (numpy). A step is taken only where L falls and stays finite, so
the result never simulates the fitted records worse than the start.
"""
from dataclasses import dataclass, replace
from typing import List, Sequence, Tuple

import numpy as np
import torch

from metampc_model.arrays import as_numpy
from metampc_model.feature_narx import FeatureNarx
from metampc_model.narx_predictor import NarxPredictor

Record = Tuple[np.ndarray, np.ndarray]      # (u (K, n_u), y (K, n_y)) physical, u[k] -> y[k]


@dataclass(frozen=True)
class OutputErrorConfig:
    """Levenberg-Marquardt on the simulation error.

    Attributes:
        iterations: at most this many accepted or refused steps.
        damping: initial mu of (J'J + mu diag(J'J)) delta = -J'r.
        rtol: stop when an accepted step lowers L by less than this, relative.
    """

    iterations: int = 50
    damping: float = 1e-3
    rtol: float = 1e-6

    def __post_init__(self):
        if self.iterations < 1 or not self.damping > 0 or not self.rtol >= 0:
            raise ValueError(f'output error needs iterations >= 1, damping > 0, rtol >= 0, '
                             f'got {self}')


@dataclass
class OutputErrorResult:
    """The refined model, its simulation loss before and after, and the losses accepted."""

    model: FeatureNarx
    loss_start: float
    loss: float
    curve: List[float]


def _free_run(model: FeatureNarx, head: np.ndarray, u: np.ndarray, y: np.ndarray
              ) -> Tuple[np.ndarray, np.ndarray]:
    """The free run over one record from its first p samples: residuals (y_sim - y) / y_std
    of samples p..K-1 ((K-p) n_y,) and their Jacobian in the head ((K-p) n_y, n_y n_phi), by
    forward sensitivities S_t = ds_t / dTheta: dy_{t+1} = y_std (I (x) phi_t') + F_s S_t, F_s
    the model's dy/ds at (s_t, u_{t+1}) (its linearisation's first rows)."""
    shape = model.shape
    p, n_y = shape.order, shape.n_y
    pred = NarxPredictor(shape, model.norm, {**model.params, 'head': head})
    y_std = np.asarray(model.norm.y_std, float)
    n_th = n_y * shape.n_phi
    s = pred.encode(u[:p], y[:p])
    sens = np.zeros((shape.n_s, n_th))
    res, jac = np.empty((len(y) - p, n_y)), np.empty((len(y) - p, n_y, n_th))
    for k in range(p, len(y)):
        lin = pred.linearise(s, u[k])
        y_next = lin.A[:n_y] @ s + lin.B[:n_y] @ u[k] + lin.e[:n_y]
        dy = lin.A[:n_y] @ sens
        phi = pred.regressors(s, u[k])
        for i in range(n_y):
            dy[i, i * shape.n_phi:(i + 1) * shape.n_phi] += y_std[i] * phi
        res[k - p], jac[k - p] = (y_next - y[k]) / y_std, dy / y_std[:, None]
        # The lags shift; the input lags are data (no sensitivity).
        sens = np.concatenate([dy, sens[:(p - 1) * n_y], np.zeros((shape.n_s - p * n_y, n_th))])
        s = pred.shift(s, y_next, u[k])
    return res.reshape(-1), jac.reshape(-1, n_th)


def refine_head(model: FeatureNarx, records: Sequence[Record],
                config: OutputErrorConfig = OutputErrorConfig()) -> OutputErrorResult:
    """The module docstring's fit from ``model``'s head, over `records` (the free run of each
    from its first p samples). ValueError: no record, or one of p samples or fewer."""
    if not records:
        raise ValueError('output error needs at least one record')
    p = model.shape.order
    records = [(np.asarray(u, float), np.asarray(y, float)) for u, y in records]
    for _, y in records:
        if len(y) <= p:
            raise ValueError(f'a record of {len(y)} samples: the free run of order {p} '
                             f'needs more than {p}')
    count = sum((len(y) - p) * model.shape.n_y for _, y in records)

    def residual(head: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
        try:
            with np.errstate(all='ignore'):     # a diverging trial run is refused by its loss
                runs = [_free_run(model, head, u, y) for u, y in records]
        except ValueError:                      # ... or by its non-finite Jacobian
            return np.inf, None, None
        r = np.concatenate([r for r, _ in runs]) / np.sqrt(count)
        jac = np.concatenate([j for _, j in runs]) / np.sqrt(count)
        loss = float(r @ r)
        return (loss if np.isfinite(loss) else np.inf), r, jac

    head = np.array(as_numpy(model.params['head'], np.float64))
    loss, r, jac = residual(head)
    start, curve, mu = loss, [loss], config.damping
    for _ in range(config.iterations):
        if not np.isfinite(loss):
            break
        jtj, jtr = jac.T @ jac, jac.T @ r
        step = np.linalg.solve(jtj + mu * np.diag(np.maximum(np.diag(jtj), 1e-12)), -jtr)
        trial = head + step.reshape(head.shape)
        trial_loss, r_trial, jac_trial = residual(trial)
        if trial_loss < loss:
            done = loss - trial_loss <= config.rtol * loss
            head, loss, r, jac, mu = trial, trial_loss, r_trial, jac_trial, mu / 3
            curve.append(loss)
            if done:
                break
        else:
            mu *= 4
    params = {**model.params, 'head': torch.from_numpy(head)}
    return OutputErrorResult(replace(model, params=params), start, loss, curve)


__all__ = ['OutputErrorConfig', 'OutputErrorResult', 'refine_head']
