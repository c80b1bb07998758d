"""The feature NARX: a one-step model linear in its head over lags and meta-learned features.

In normalised units, with s_t = [y_t .. y_{t-p+1}, u_t .. u_{t-p+2}] the ARX's regressor state
(n_s = p n_y + (p - 1) n_u; u_k the input that produced y_k):

    y_{t+1} = Theta phi(s_t, u_{t+1}),   phi = [s_t; g(s_t); u_{t+1}; 1]   (n_phi = n_s+F+n_u+1)

g a tanh MLP of F features (fixed during adaptation), Theta (n_y, n_phi) the head, solved in
closed form (:mod:`metampc_learner.closed_form`); with g's columns zero it is the ARX(p). Smooth,
so the MPC plans on its linearisation at the current state (:meth:`FeatureNarx.linearise`,
:mod:`metampc_controller.local_mpc`); its numpy evaluation (the controller's, no torch) is
:mod:`metampc_model.narx_predictor`. Why and what it measured: docs/nonlinear.md.
"""
from dataclasses import dataclass
from typing import Dict, Optional, Tuple

import numpy as np
import torch

from metampc_model.latent_model import LatentModel
from metampc_model.narx_predictor import NarxPredictor
from metampc_model.narx_shape import NarxShape
from metampc_model.normalisation import Normalisation

Params = Dict[str, torch.Tensor]


def init_params(shape: NarxShape, seed: int, dtype=torch.float64) -> Params:
    """Seeded initial parameters: g's layers uniform in +-1/sqrt(fan_in) (PyTorch's default),
    'head' zero (the meta-model's prior head starts at the zero model)."""
    gen = torch.Generator().manual_seed(int(seed))
    params = {}
    for name, s in shape.feature_shapes().items():
        fan_in = s[-1] if name.endswith('weight') else params[name[:-4] + 'weight'].shape[1]
        params[name] = (torch.rand(s, generator=gen, dtype=dtype) * 2 - 1) / np.sqrt(fan_in)
    params['head'] = torch.zeros((shape.n_y, shape.n_phi), dtype=dtype)
    return params


def features(shape: NarxShape, params: Params, s: torch.Tensor) -> torch.Tensor:
    """g(s): s (..., n_s) normalised -> (..., F)."""
    n_layers = len(shape.hidden) + 1
    h = s
    for i in range(n_layers):
        h = torch.nn.functional.linear(h, params[f'g.{i}.weight'], params[f'g.{i}.bias'])
        h = torch.tanh(h)
    return h


def regressors(shape: NarxShape, params: Params, s: torch.Tensor, u_next: torch.Tensor
               ) -> torch.Tensor:
    """phi(s_t, u_{t+1}): s (..., n_s), u_next (..., n_u) normalised -> (..., n_phi)."""
    parts = [s]
    if shape.features:
        parts.append(features(shape, params, s))
    parts += [u_next, torch.ones(s.shape[:-1] + (1,), dtype=s.dtype)]
    return torch.cat(parts, dim=-1)


def shift_state(shape: NarxShape, s: torch.Tensor, y_next: torch.Tensor,
                u_next: torch.Tensor) -> torch.Tensor:
    """s_{t+1} from s_t (..., n_s), y_{t+1} (..., n_y) and u_{t+1} (..., n_u)."""
    p, n_y = shape.order, shape.n_y
    ys = torch.cat([y_next, s[..., :(p - 1) * n_y]], dim=-1)
    if p == 1:
        return ys
    us = torch.cat([u_next, s[..., p * n_y:p * n_y + (p - 2) * shape.n_u]], dim=-1)
    return torch.cat([ys, us], dim=-1)


def rollout(shape: NarxShape, params: Params, s: torch.Tensor, u_future: torch.Tensor,
            head: Optional[torch.Tensor] = None) -> torch.Tensor:
    """T-step prediction: s_t (..., n_s), u_{t+1..t+T} (..., T, n_u) -> y_hat (..., T, n_y);
    `head` (..., n_y, n_phi) in place of params['head'] (a task's adapted head)."""
    head = params['head'] if head is None else head
    out = []
    for k in range(u_future.shape[-2]):
        u = u_future[..., k, :]
        y = (head @ regressors(shape, params, s, u)[..., None])[..., 0]
        out.append(y)
        s = shift_state(shape, s, y, u)
    return torch.stack(out, dim=-2)


def state_windows(shape: NarxShape, u: np.ndarray, y: np.ndarray, horizon: int
                  ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every window of one trajectory (u (K, n_u), y (K, n_y), u[k] produced y[k]):
    (s_t (M, n_s), u_{t+1..t+T} (M, T, n_u), y_{t+1..t+T} (M, T, n_y)), t = p-1 .. K-1-T."""
    p = shape.order
    ts = np.arange(p - 1, len(y) - horizon)
    if ts.size == 0:
        return (np.zeros((0, shape.n_s)), np.zeros((0, horizon, shape.n_u)),
                np.zeros((0, horizon, shape.n_y)))
    s = np.concatenate([y[ts - i] for i in range(p)] + [u[ts - j] for j in range(p - 1)],
                       axis=1)
    k = ts[:, None] + np.arange(1, horizon + 1)[None, :]
    return s, u[k], y[k]


@dataclass
class FeatureNarx:
    """A feature NARX with its normalisation, evaluated in float64 numpy for the controller.

    Attributes:
        shape: its sizes.
        norm: physical <-> normalised units.
        params: g's parameters and 'head' (tensors, float64).
    """

    shape: NarxShape
    norm: Normalisation
    params: Params

    @property
    def predictor(self) -> NarxPredictor:
        """The numpy evaluation of this model (float64, :mod:`metampc_model.narx_predictor`:
        the controller's), of its params as they are now."""
        return NarxPredictor(self.shape, self.norm, self.params)

    def state(self, u_hist: np.ndarray, y_hist: np.ndarray) -> np.ndarray:
        """Physical s_t from the last p outputs y (p, n_y) and inputs u (p, n_u), oldest
        first (u_hist[-1] = u_t)."""
        return self.predictor.encode(u_hist, y_hist)

    def step(self, s: np.ndarray, u_next: np.ndarray) -> np.ndarray:
        """y_{t+1} (n_y,) physical from s_t (n_s,) and u_{t+1} (n_u,) physical."""
        return self.predictor.step(s, u_next)

    def linearise(self, s: np.ndarray, u_next: np.ndarray) -> LatentModel:
        """:meth:`NarxPredictor.linearise`: the affine model exact to first order at
        (s, u_next), physical units; ValueError if the Jacobian is not finite."""
        return self.predictor.linearise(s, u_next)


__all__ = ['NarxShape', 'FeatureNarx', 'init_params', 'features', 'regressors', 'rollout',
           'shift_state', 'state_windows']
