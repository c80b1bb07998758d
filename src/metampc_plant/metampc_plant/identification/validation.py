"""The baselines' validation protocol on one record (u, y of shape (N,)): fit on its head,
score on its tail.

Samples 0..fit_samples-1 fit a model, samples validation_start..N-1 score it (fit_samples <=
validation_start: no scored sample was fitted). Two figures, the output's units: simulation RMSE
(the model run free from sample 0 over the whole record, grey-box from its fitted x[0], ARX from
the first lag measured outputs; scored on the tail) and T-step prediction RMSE (each origin t
with t+1..t+T in the tail: y[t+1..t+T] from the data up to t and the inputs; squared errors
averaged over origins and steps). ARX orders are chosen on the tail's simulation RMSE (the
benchmark's figure of merit). docs/real_data.md.
"""
from dataclasses import dataclass
import itertools
from typing import Optional, Sequence, Tuple

import numpy as np

from metampc_plant.family import PlantFamily
from metampc_plant.identification.arx import Arx, fit_arx, predict_arx, simulate_arx
from metampc_plant.identification.greybox import (fit_greybox, GreyBoxFit, predict_greybox,
                                                  simulate_family)


@dataclass(frozen=True)
class Protocol:
    """What is fitted, what is scored and how.

    Attributes:
        fit_samples: samples 0..fit_samples-1 fit the models.
        validation_start: samples validation_start..N-1 score them (>= fit_samples).
        history: H, samples up to an origin a T-step predictor may read (the NSSM's window).
        horizon: T, samples predicted from each origin.
        max_order: ARX na and nb searched in 1..max_order.
        max_delay: ARX nk searched in 0..max_delay.
        candidates: grey-box candidates scored first: theta log-uniform within a factor
            `spread` of a guess, x[0] uniform in the family's x0_low..x0_high (the measured
            components from y[0]), drawn with rng(`seed`).
        polish: grey-box least-squares searches, from the best candidates.
        spread: see candidates (> 1).
        seed: see candidates.
        substeps: RK4 steps per sample of the grey-box model.
    """

    fit_samples: int = 768
    validation_start: int = 768
    history: int = 10
    horizon: int = 10
    max_order: int = 4
    max_delay: int = 1
    candidates: int = 512
    polish: int = 4
    spread: float = 2.0
    seed: int = 0
    substeps: int = 4

    def check(self, n: int) -> None:
        """ValueError naming the first setting that does not fit a record of n samples."""
        if not 20 <= self.fit_samples <= self.validation_start <= n - self.horizon - 1:
            raise ValueError(f'need 20 <= fit_samples ({self.fit_samples}) <= validation_start '
                             f'({self.validation_start}) <= {n - self.horizon - 1} (N - T - 1)')
        if min(self.history, self.horizon, self.max_order, self.candidates, self.polish,
               self.substeps) < 1 or self.max_delay < 0 or self.seed < 0 or not self.spread > 1:
            raise ValueError('history, horizon, max_order, candidates, polish and substeps must '
                             'be >= 1, max_delay and seed >= 0, spread > 1')
        if self.max_order + self.max_delay > self.history:
            raise ValueError(f'ARX lags up to max_order + max_delay = '
                             f'{self.max_order + self.max_delay} exceed history {self.history}')

    def origins(self, n: int) -> np.ndarray:
        """The T-step origins t: t + 1 .. t + T in the tail, t - H + 1 >= 0."""
        return np.arange(max(self.validation_start - 1, self.history - 1), n - self.horizon)


@dataclass(frozen=True)
class Scores:
    """A model's figures on the tail, the output's units."""

    simulation_rmse: float
    prediction_rmse: float


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean square of a - b (inf if not finite)."""
    with np.errstate(over='ignore', invalid='ignore'):
        value = float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))
    return value if np.isfinite(value) else float('inf')


def arx_baseline(u: np.ndarray, y: np.ndarray, protocol: Protocol) -> Tuple[Arx, Scores]:
    """The ARX model of the orders whose simulation scores best on the tail, and its scores."""
    protocol.check(len(y))
    head, tail = slice(0, protocol.fit_samples), slice(protocol.validation_start, None)
    best, best_rmse = None, float('inf')
    orders = itertools.product(range(1, protocol.max_order + 1),
                               range(1, protocol.max_order + 1), range(protocol.max_delay + 1))
    for na, nb, nk in orders:
        model = fit_arx(u[head], y[head], na, nb, nk)
        with np.errstate(over='ignore', invalid='ignore'):
            score = rmse(simulate_arx(model, u, y)[tail], y[tail])
        if score < best_rmse:
            best, best_rmse = model, score
    origins = protocol.origins(len(y))
    predicted = predict_arx(best, u, y, origins, protocol.horizon)
    measured = y[origins[:, None] + np.arange(1, protocol.horizon + 1)]
    return best, Scores(best_rmse, rmse(predicted, measured))


def fit_greybox_head(family: PlantFamily, u: np.ndarray, y: np.ndarray, n: int,
                     protocol: Protocol, theta_guess: Sequence[float],
                     theta_bounds: Optional[Tuple[Sequence[float], Sequence[float]]] = None
                     ) -> GreyBoxFit:
    """The family member fitted to samples 0..n-1 of (u, y) (N,): the protocol's candidates
    around `theta_guess` and initial states, then its least-squares searches."""
    u2, y2 = np.asarray(u, dtype=float)[:, None], np.asarray(y, dtype=float)[:, None]
    rng = np.random.default_rng(protocol.seed)
    size = (protocol.candidates, family.n_theta)
    thetas = np.asarray(theta_guess, dtype=float) * np.exp(
        rng.uniform(-np.log(protocol.spread), np.log(protocol.spread), size))
    levels = rng.uniform(family.x0_low, family.x0_high, (protocol.candidates, family.n_x))
    x0s = np.array([family.state_from_output(y2[0], x) for x in levels])
    return fit_greybox(family, u2[:n], y2[:n], thetas, x0s, theta_bounds, protocol.substeps,
                       protocol.polish)


def greybox_baseline(family: PlantFamily, u: np.ndarray, y: np.ndarray, protocol: Protocol,
                     theta_guess: Sequence[float],
                     theta_bounds: Optional[Tuple[Sequence[float], Sequence[float]]] = None
                     ) -> Tuple[GreyBoxFit, Scores]:
    """The family member fitted to the head (candidates around `theta_guess`), its scores."""
    protocol.check(len(y))
    u2, y2 = np.asarray(u, dtype=float)[:, None], np.asarray(y, dtype=float)[:, None]
    fit = fit_greybox_head(family, u, y, protocol.fit_samples, protocol, theta_guess,
                           theta_bounds)
    x_sim, y_sim = simulate_family(family, fit.theta[None], fit.x0[None], u2, protocol.substeps)
    origins = protocol.origins(len(y))
    predicted = predict_greybox(family, fit.theta, u2, y2, origins, protocol.history,
                                protocol.horizon, x_sim[0], protocol.substeps)
    measured = y2[origins[:, None] + np.arange(1, protocol.horizon + 1)]
    tail = slice(protocol.validation_start, None)
    return fit, Scores(rmse(y_sim[0, tail], y2[tail]), rmse(predicted, measured))


__all__ = ['Protocol', 'Scores', 'rmse', 'arx_baseline', 'fit_greybox_head',
           'greybox_baseline']
