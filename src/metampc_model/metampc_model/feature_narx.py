"""The feature NARX: a one-step model linear in its head over lags and meta-learned features.

In normalised units, with s_t = [y_t .. y_{t-p+1}, u_t .. u_{t-p+2}] the ARX's regressor state
(n_s = p n_y + (p - 1) n_u; u_k the input that produced y_k):

    y_{t+1} = Theta phi(s_t, u_{t+1}),   phi = [s_t; g(s_t); u_{t+1}; 1]   (n_phi = n_s+F+n_u+1)

g a tanh MLP of F features (fixed during adaptation), Theta (n_y, n_phi) the head, solved in
closed form (:mod:`metampc_learner.closed_form`); with g's columns zero it is the ARX(p). Smooth,
so the MPC plans on its linearisation at the current state (:meth:`FeatureNarx.linearise`,
:mod:`metampc_controller.local_mpc`). Why and what it measured: docs/nonlinear.md.
"""
from dataclasses import dataclass, field
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import torch

from metampc_model.latent_model import LatentModel
from metampc_model.normalisation import Normalisation

Params = Dict[str, torch.Tensor]


@dataclass(frozen=True)
class NarxShape:
    """Sizes of a feature NARX.

    Attributes:
        n_u, n_y: inputs, outputs.
        order: p, lags of the regressor state (>= 1).
        features: F, meta-learned features (0: the ARX).
        hidden: widths of g's hidden tanh layers.
    """

    n_u: int
    n_y: int
    order: int = 2
    features: int = 16
    hidden: Tuple[int, ...] = field(default=(64,))

    def __post_init__(self):
        if min(self.n_u, self.n_y, self.order) < 1 or self.features < 0 or any(
                w < 1 for w in self.hidden):
            raise ValueError(f'feature NARX needs n_u, n_y, order >= 1, features >= 0 and '
                             f'hidden widths >= 1, got {self}')

    @property
    def n_s(self) -> int:
        """Size of the regressor state s_t."""
        return self.order * self.n_y + (self.order - 1) * self.n_u

    @property
    def n_phi(self) -> int:
        """Size of the regressor phi."""
        return self.n_s + self.features + self.n_u + 1

    def feature_shapes(self) -> Dict[str, Tuple[int, ...]]:
        """g's parameters, canonical order: g.<i>.weight (out, in), g.<i>.bias (out,)."""
        widths = [self.n_s, *self.hidden, self.features]
        shapes = {}
        for i in range(len(widths) - 1):
            shapes[f'g.{i}.weight'] = (widths[i + 1], widths[i])
            shapes[f'g.{i}.bias'] = (widths[i + 1],)
        return shapes if self.features else {}


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

    def state(self, u_hist: np.ndarray, y_hist: np.ndarray) -> np.ndarray:
        """Physical s_t from the last p outputs y (p, n_y) and inputs u (p, n_u), oldest
        first (u_hist[-1] = u_t)."""
        p = self.shape.order
        ys = [y_hist[-1 - i] for i in range(p)]
        us = [u_hist[-1 - j] for j in range(p - 1)]
        return np.concatenate(ys + us) if us else np.concatenate(ys)

    def _scales(self) -> Tuple[np.ndarray, np.ndarray]:
        """(mean, std) of s_t's entries, (n_s,) each."""
        p, nm = self.shape.order, self.norm
        mean = np.concatenate([nm.y_mean] * p + [nm.u_mean] * (p - 1))
        std = np.concatenate([nm.y_std] * p + [nm.u_std] * (p - 1))
        return mean, std

    def _normalised(self, s: np.ndarray, u_next: np.ndarray) -> Tuple[np.ndarray, ...]:
        """(s_n, u_n, layers of g) for the numpy evaluation: the layers' (weight, bias) as
        arrays sharing memory with the tensors."""
        mean, std = self._scales()
        nm = self.norm
        layers = [(self.params[f'g.{i}.weight'].detach().numpy(),
                   self.params[f'g.{i}.bias'].detach().numpy())
                  for i in range(len(self.shape.hidden) + 1)] if self.shape.features else []
        return ((s - mean) / std, (np.asarray(u_next, float) - nm.u_mean) / nm.u_std, layers)

    def _one_step(self, s_n: np.ndarray, u_n: np.ndarray, layers
                  ) -> Tuple[np.ndarray, np.ndarray]:
        """(y_n (n_y,), dg/ds_n (F, n_s)): g and its Jacobian through the tanh layers,
        prod_i diag(1 - h_{i+1}^2) W_i, in float64 numpy (no autograd on the tick)."""
        h, jac = s_n, np.eye(s_n.size)
        for w, b in layers:
            h = np.tanh(w @ h + b)
            jac = (1.0 - h * h)[:, None] * (w @ jac)
        head = self.params['head'].detach().numpy()
        phi = np.concatenate([s_n, h if layers else np.zeros(0), u_n, [1.0]])
        return head @ phi, jac if layers else np.zeros((0, s_n.size))

    def step(self, s: np.ndarray, u_next: np.ndarray) -> np.ndarray:
        """y_{t+1} (n_y,) physical from s_t (n_s,) and u_{t+1} (n_u,) physical."""
        s_n, u_n, layers = self._normalised(s, u_next)
        return self._one_step(s_n, u_n, layers)[0] * self.norm.y_std + self.norm.y_mean

    def linearise(self, s: np.ndarray, u_next: np.ndarray) -> LatentModel:
        """The affine model of s_{t+1} = F(s_t, u_{t+1}) at (s, u_next), physical units:
        z = s, z+ = A z + B u + e exact to first order there (A the companion matrix whose
        first n_y rows are dF/ds), y = C z (C selects y_t), d = 0. ValueError if the
        Jacobian is not finite."""
        sh, nm = self.shape, self.norm
        _, std = self._scales()
        s_n, u_n, layers = self._normalised(s, u_next)
        y_n, jac_g = self._one_step(s_n, u_n, layers)
        head = self.params['head'].detach().numpy()
        n_s, n_f, n_y, n_u, p = sh.n_s, sh.features, sh.n_y, sh.n_u, sh.order
        j_s = head[:, :n_s] + head[:, n_s:n_s + n_f] @ jac_g
        j_u = head[:, n_s + n_f:n_s + n_f + n_u]
        top_s = j_s * nm.y_std[:, None] / std[None, :]
        top_u = j_u * nm.y_std[:, None] / nm.u_std[None, :]
        y_next = y_n * nm.y_std + nm.y_mean
        if not all(np.all(np.isfinite(v)) for v in (top_s, top_u, y_next)):
            raise ValueError('the feature NARX has a non-finite Jacobian here')
        u_next = np.asarray(u_next, float)
        A = np.zeros((n_s, n_s))
        B = np.zeros((n_s, n_u))
        e = np.zeros(n_s)
        A[:n_y], B[:n_y] = top_s, top_u
        e[:n_y] = y_next - top_s @ s - top_u @ u_next
        A[n_y:p * n_y, :(p - 1) * n_y] = np.eye((p - 1) * n_y)     # y lags shift
        if p > 1:
            B[p * n_y:p * n_y + n_u] = np.eye(n_u)                 # u_{t+1} becomes a lag
            A[p * n_y + n_u:, p * n_y:n_s - n_u] = np.eye((p - 2) * n_u)
        C = np.zeros((n_y, n_s))
        C[:, :n_y] = np.eye(n_y)
        return LatentModel(A, B, C, e, np.zeros(n_y))


def physical_windows(shape: NarxShape, norm: Normalisation,
                     trajectories: Sequence[Tuple[np.ndarray, np.ndarray]], horizon: int
                     ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Normalised windows of several trajectories ((u, y) pairs, physical), concatenated:
    (s (M, n_s), u_future (M, T, n_u), y_future (M, T, n_y)), float64 tensors."""
    parts = [state_windows(shape, *norm.normalise(u, y), horizon) for u, y in trajectories]
    return tuple(torch.from_numpy(np.concatenate([p[i] for p in parts])) for i in range(3))


__all__ = ['NarxShape', 'FeatureNarx', 'init_params', 'features', 'regressors', 'rollout',
           'shift_state', 'state_windows', 'physical_windows']
