"""The feature NARX on measured records: free-run simulation and T-step prediction.

A record (u (N, n_u), y (N, n_y)), physical, in the data convention of
:mod:`metampc_model.feature_narx` (u[k] the input that produced y[k]). Both functions read the
measured record only where a model may: the simulation its first p samples (the initial
state s_{p-1}), the predictor the samples up to each origin; everything after comes from the
model's own outputs (:func:`metampc_model.feature_narx.rollout`). Used by
``studies/cascaded_tanks_narx.py`` (docs/real_data.md).
"""
from typing import Sequence

import numpy as np
import torch

from metampc_model.feature_narx import FeatureNarx, rollout, state_windows


def _predict(model: FeatureNarx, u: np.ndarray, y: np.ndarray, origins: np.ndarray,
             horizon: int) -> np.ndarray:
    """y_hat[t+1..t+horizon] (len(origins), horizon, n_y), physical, from the states s_t."""
    s, u_future, _ = state_windows(model.shape, *model.norm.normalise(u, y), horizon)
    first = model.shape.order - 1        # the state of the first window is s_{p-1}
    with torch.no_grad():
        y_n = rollout(model.shape, model.params, torch.from_numpy(s[origins - first]),
                      torch.from_numpy(u_future[origins - first]))
    return model.norm.denormalise_y(y_n.numpy())


def free_run(model: FeatureNarx, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Free-run simulation over a record: y_hat (N, n_y), its first p rows the measured
    y[0..p-1] (with u[1..p-1], the initial state), every later row the model's from its own
    outputs and u[p..N-1]. ValueError: a record of p samples or fewer."""
    p = model.shape.order
    if len(y) <= p:
        raise ValueError(f'free run of a NARX of order {p} needs more than {p} samples, '
                         f'got {len(y)}')
    u, y = np.asarray(u, float), np.asarray(y, float)
    return np.concatenate([y[:p], _predict(model, u, y, np.array([p - 1]), len(y) - p)[0]])


def predict(model: FeatureNarx, u: np.ndarray, y: np.ndarray, origins: Sequence[int],
            horizon: int) -> np.ndarray:
    """T-step predictions: for each origin t (p-1 <= t <= N-1-horizon), y[t+1..t+horizon]
    from the measured record up to t and the inputs after it: (len(origins), horizon, n_y).
    ValueError: an origin out of that range."""
    origins = np.asarray(origins, dtype=int)
    low, high = model.shape.order - 1, len(y) - 1 - horizon
    if origins.size == 0 or origins.min() < low or origins.max() > high or horizon < 1:
        raise ValueError(f'T-step origins need {low} <= t <= {high} and a horizon >= 1, got '
                         f'{origins.min(initial=0)}..{origins.max(initial=0)}, {horizon}')
    return _predict(model, np.asarray(u, float), np.asarray(y, float), origins, horizon)


__all__ = ['free_run', 'predict']
