"""Grey-box identification of a plant family: theta and x(0) by simulation-error least squares.

The model is the family's own simulator (:class:`~metampc_plant.simulator.BatchPlant`, RK4 with
the input held): x[k+1] = F(x[k], u[k]), y[k] = g(x[k]), u[k] held over [k dt, (k+1) dt).
:func:`fit_greybox` minimises the free-run output error over (theta, x[0]): candidates scored in
one batched simulation (the error has local minima), scipy.optimize.least_squares from the best
few, forward-difference Jacobians of all parameters in one batched simulation.
:func:`predict_greybox` is the T-step predictor: the state at each window's start fitted to its
H measured outputs, then run T samples on. Arrays u (N, n_u), y (N, n_y). Pure numpy/scipy.
"""
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import block_diag

from metampc_plant.family import PlantFamily
from metampc_plant.simulator import BatchPlant, PlantConfig

STEP = np.sqrt(np.finfo(float).eps)   # forward-difference step, relative to max(|p|, 1)


@dataclass(frozen=True)
class GreyBoxFit:
    """A fitted member of a family.

    Attributes:
        theta: (n_theta,) parameters.
        x0: (n_x,) state at the first fitted sample.
        rmse: free-run output RMSE over the fitted samples, the outputs' units.
        evaluations: simulations run (each of a batch counted once).
    """

    theta: np.ndarray
    x0: np.ndarray
    rmse: float
    evaluations: int


def simulate_family(family: PlantFamily, thetas: np.ndarray, x0: np.ndarray, u: np.ndarray,
                    substeps: int) -> Tuple[np.ndarray, np.ndarray]:
    """B members of `family` run open loop.

    Args:
        thetas: (B, n_theta); x0: (B, n_x) states at sample 0.
        u: (N, n_u) inputs shared by all, or (B, N, n_u) one sequence each; u[k] held over
            [k dt, (k+1) dt) (u[N-1] unused).

    Returns:
        (x, y): states (B, N, n_x) and outputs (B, N, n_y) at samples 0..N-1.

    Raises:
        ValueError: an input outside the family's bounds (the plant would clip it).
    """
    thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
    u = np.asarray(u, dtype=float)
    u = np.broadcast_to(u, (len(thetas),) + u.shape) if u.ndim == 2 else u
    if np.any(u < np.asarray(family.u_min)) or np.any(u > np.asarray(family.u_max)):
        raise ValueError(f'inputs in [{u.min():g}, {u.max():g}] leave the bounds '
                         f'[{list(family.u_min)}, {list(family.u_max)}] of family {family.name}')
    plant = BatchPlant(thetas, PlantConfig(family=family.name, substeps=substeps), x0)
    xs, ys = [plant.x.copy()], [plant.output()]
    for k in range(u.shape[1] - 1):
        ys.append(plant.step(u[:, k]))
        xs.append(plant.x.copy())
    return np.stack(xs, axis=1), np.stack(ys, axis=1)


def fit_greybox(family: PlantFamily, u: np.ndarray, y: np.ndarray, thetas: np.ndarray,
                x0s: np.ndarray, theta_bounds: Optional[Tuple[Sequence[float],
                                                              Sequence[float]]] = None,
                substeps: int = 4, polish: int = 4) -> GreyBoxFit:
    """theta and x[0] minimising sum_k |y_model[k] - y[k]|^2 over the N samples of u, y.

    Args:
        thetas, x0s: (S, n_theta), (S, n_x) candidates, all simulated in one batch.
        theta_bounds: (low, high) of theta, each (n_theta,) (default unbounded); x[0] is kept
            within the family's state box.
        polish: least-squares searches, from the best candidates; the best result is returned.
    """
    n_theta, n_x = family.n_theta, family.n_x
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    low, high = theta_bounds if theta_bounds is not None else (
        np.full(n_theta, -np.inf), np.full(n_theta, np.inf))
    bounds = (np.concatenate([low, np.full(n_x, -family.state_bound)]),
              np.concatenate([high, np.full(n_x, family.state_bound)]))
    evaluations = 0

    def outputs(params: np.ndarray) -> np.ndarray:
        nonlocal evaluations
        evaluations += 1
        return simulate_family(family, params[:, :n_theta], params[:, n_theta:], u,
                               substeps)[1].reshape(len(params), -1)

    def residual(p: np.ndarray) -> np.ndarray:
        return outputs(p[None])[0] - y.reshape(-1)

    def jacobian(p: np.ndarray) -> np.ndarray:
        step = STEP * np.maximum(np.abs(p), 1.0)
        ys = outputs(np.vstack([p, p + np.diag(step)]))
        return ((ys[1:] - ys[0]) / step[:, None]).T

    candidates = np.clip(np.hstack([np.atleast_2d(thetas), np.atleast_2d(x0s)]), *bounds)
    with np.errstate(over='ignore', invalid='ignore'):
        costs = np.nan_to_num(np.sum((outputs(candidates) - y.reshape(-1)) ** 2, axis=1),
                              nan=np.inf)
    best = None
    for start in candidates[np.argsort(costs, kind='stable')[:polish]]:
        result = least_squares(residual, start, jac=jacobian, bounds=bounds, x_scale='jac')
        if best is None or result.cost < best.cost:
            best = result
    return GreyBoxFit(theta=best.x[:n_theta], x0=best.x[n_theta:],
                      rmse=float(np.sqrt(2.0 * best.cost / y.size)), evaluations=evaluations)


def predict_greybox(family: PlantFamily, theta: Sequence[float], u: np.ndarray, y: np.ndarray,
                    origins: Sequence[int], history: int, horizon: int, x_guess: np.ndarray,
                    substeps: int = 4) -> np.ndarray:
    """T-step predictions: for each origin t, y[t+1..t+horizon], shape (len(origins), horizon,
    n_y).

    The state at t - history + 1 is fitted (least squares, from x_guess[t - history + 1]) to
    the measured y[t-history+1..t], then the model runs on with the inputs to t + horizon.

    Args:
        x_guess: (N, n_x) a state guess per sample, e.g. a free-run simulation's.

    Raises:
        ValueError: an origin closer than history - 1 to the start or than horizon to the end.
    """
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    origins = np.asarray(origins, dtype=int)
    if origins.size == 0 or origins.min() < history - 1 or origins.max() > len(y) - 1 - horizon:
        raise ValueError(f'T-step origins need {history - 1} <= t <= {len(y) - 1 - horizon}')
    n_x, n_w = family.n_x, len(origins)
    window = origins[:, None] + np.arange(1 - history, horizon + 1)     # (W, H + T)
    thetas = np.tile(np.asarray(theta, dtype=float), (n_w, 1))
    seen = y[window[:, :history]].reshape(-1)

    def run(states: np.ndarray, samples: int) -> np.ndarray:
        return simulate_family(family, thetas, states.reshape(n_w, n_x),
                               u[window[:, :samples]], substeps)[1]

    # One problem over all windows, its Jacobian block-diagonal (scipy perturbs every window at
    # once: n_x + 1 batched simulations a Jacobian). On the benchmark's tail, tolerances 100x
    # tighter moved the 10-step RMSE by 2e-6 V.
    fitted = least_squares(lambda z: run(z, history).reshape(-1) - seen,
                           x_guess[window[:, 0]].reshape(-1),
                           jac_sparsity=block_diag([np.ones((history * family.n_y, n_x))] * n_w),
                           bounds=(-family.state_bound, family.state_bound))
    return run(fitted.x, history + horizon)[:, history:]


__all__ = ['GreyBoxFit', 'simulate_family', 'fit_greybox', 'predict_greybox']
