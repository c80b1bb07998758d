"""Linear ARX models: least-squares fit, simulation, T-step prediction.

    y[k] = a_1 y[k-1] + ... + a_na y[k-na] + b_0 u[k-nk] + ... + b_(nb-1) u[k-nk-nb+1] + c

(c an offset: the data need not be centred). Fitted by ordinary least squares on the one-step
equation error (numpy.linalg.lstsq; :func:`least_squares` for any numbers of inputs and
outputs and several records, the learner's `arx` method uses it too); the single-input,
single-output :class:`Arx` runs either in free simulation (each y from the model's own earlier
outputs) or as a T-step predictor (measured outputs up to the origin, the model's own after it).
u[k] and y[k] share the index k; nk = 1 makes u[k] act on y[k+1] first. Pure numpy.
"""
from dataclasses import dataclass
from typing import Sequence, Tuple

import numpy as np


@dataclass(frozen=True)
class Arx:
    """An ARX model (see the module docstring).

    Attributes:
        a: (na,) output coefficients a_1..a_na.
        b: (nb,) input coefficients b_0..b_(nb-1).
        nk: input delay, samples (>= 0).
        c: offset.
    """

    a: np.ndarray
    b: np.ndarray
    nk: int
    c: float

    @property
    def lag(self) -> int:
        """Samples of the past a prediction needs: max(na, nk + nb - 1) (>= 1)."""
        return _lag(len(self.a), len(self.b), self.nk)


def _lag(na: int, nb: int, nk: int) -> int:
    """The first sample an ARX(na, nb, nk) equation can be written for."""
    return max(na, nk + nb - 1, 1)


def _check(u: np.ndarray, y: np.ndarray):
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    if u.ndim != 1 or u.shape != y.shape or not np.all(np.isfinite(u) & np.isfinite(y)):
        raise ValueError(f'ARX needs finite u and y of one shape (N,), got {u.shape}, {y.shape}')
    return u, y


def least_squares(records: Sequence[Tuple[np.ndarray, np.ndarray]], na: int, nb: int, nk: int
                  ) -> np.ndarray:
    """Least-squares ARX(na, nb, nk) with offset, any numbers of inputs and outputs: over every
    k >= lag of each record (u (N, n_u), y (N, n_y)), records never mixed in one equation.

    Returns:
        theta (n_y, na n_y + nb n_u + 1): [a_1 .. a_na (each n_y columns), b_0 .. b_(nb-1)
        (each n_u columns), c].

    Raises:
        ValueError: na < 0, nb < 1, nk < 0, or fewer equations than unknowns.
    """
    if na < 0 or nb < 1 or nk < 0:
        raise ValueError(f'ARX orders need na >= 0, nb >= 1, nk >= 0, got {na}, {nb}, {nk}')
    lag = _lag(na, nb, nk)
    rows, targets = [], []
    for u, y in records:
        ks = np.arange(lag, len(y))
        rows.append(np.concatenate([y[ks - i] for i in range(1, na + 1)]
                                   + [u[ks - nk - j] for j in range(nb)]
                                   + [np.ones((len(ks), 1))], axis=1))
        targets.append(y[ks])
    x, y = np.concatenate(rows), np.concatenate(targets)
    if len(x) < x.shape[1]:
        raise ValueError(f'ARX({na}, {nb}, {nk}) needs more than {lag + x.shape[1] - 1} '
                         f'samples in a record (or records of more than {lag}), got '
                         f'{len(x)} equations for {x.shape[1]} unknowns per output')
    return np.linalg.lstsq(x, y, rcond=None)[0].T


def fit_arx(u: Sequence[float], y: Sequence[float], na: int, nb: int, nk: int) -> Arx:
    """Least-squares ARX(na, nb, nk) with offset on samples k = lag .. N-1 of u, y (N,).

    Raises:
        ValueError: na < 0, nb < 1, nk < 0, or fewer equations than unknowns.
    """
    u, y = _check(u, y)
    coef = least_squares([(u[:, None], y[:, None])], na, nb, nk)[0]
    return Arx(a=coef[:na], b=coef[na:na + nb], nk=nk, c=float(coef[-1]))


def predict_arx(model: Arx, u: Sequence[float], y: Sequence[float], origins: Sequence[int],
                horizon: int) -> np.ndarray:
    """T-step predictions: for each origin t, y[t+1..t+horizon] from the measured y[..t] and
    u[..t+horizon], shape (len(origins), horizon).

    Raises:
        ValueError: an origin with fewer than ``model.lag`` samples up to it, or beyond
            N - 1 - horizon.
    """
    u, y = _check(u, y)
    origins = np.asarray(origins, dtype=int)
    lag = model.lag
    if horizon < 1 or origins.size == 0 or origins.min() < lag - 1 or (
            origins.max() > len(y) - 1 - horizon):
        raise ValueError(f'T-step origins need {lag - 1} <= t <= {len(y) - 1 - horizon} and '
                         f'a horizon >= 1, got t in [{origins.min(initial=0)}, '
                         f'{origins.max(initial=0)}], horizon {horizon}')
    # Column lag - 1 + j of `track` holds y[t + j]: measured for j <= 0, predicted after.
    track = np.concatenate([y[origins[:, None] + np.arange(1 - lag, 1)],
                            np.zeros((len(origins), horizon))], axis=1)
    for j in range(1, horizon + 1):
        col = lag - 1 + j
        k = origins + j
        value = np.full(len(origins), model.c)
        for i, a in enumerate(model.a, start=1):
            value += a * track[:, col - i]
        for i, b in enumerate(model.b):
            value += b * u[k - model.nk - i]
        track[:, col] = value
    return track[:, lag:]


def simulate_arx(model: Arx, u: Sequence[float], y_init: Sequence[float]) -> np.ndarray:
    """Free-run simulation over u (N,): the first ``model.lag`` outputs are y_init's (the
    initial conditions), every later one the model's from its own outputs; shape (N,)."""
    u = np.asarray(u, dtype=float)
    start = np.zeros(len(u))
    start[:model.lag] = np.asarray(y_init, dtype=float)[:model.lag]
    rest = predict_arx(model, u, start, [model.lag - 1], len(u) - model.lag)[0]
    return np.concatenate([start[:model.lag], rest])


__all__ = ['Arx', 'fit_arx', 'least_squares', 'predict_arx', 'simulate_arx']
