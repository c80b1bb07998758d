"""Neural state-space model (NSSM) of the paper, eq. (SSM): the MPC's predictive model.

In normalised units (:mod:`metampc_model.normalisation`): z_t = f_enc(u, y over t-H+1..t)
(eq. (z), an MLP with ReLU hidden layers), z_{t+1} = A z_t + B u_{t+1} (eq. (z_next)),
y_hat_t = C z_t (eq. (haty)); the loss l_SSM = 1/T ||Y_{t+1:t+T} - Y_hat_{t+1:t+T}||^2 (summed
over the n_y outputs, averaged over T and the windows), plus the optional latent consistency
term (``consistency_weight``, :func:`training_loss`). A window holds H + T samples
``(u, y)[t-H+1 .. t+T]``, u_k the input held over ((k-1) dt, k dt] that produced y_k: u of
shape (batch, H + T, n_u), y (batch, H + T, n_y). Parameters are a ``Dict[str, Tensor]`` in
the order of :func:`param_shapes` (encoder.<i>.weight/bias, A, B, C), usable with
``torch.func.functional_call``. Conventions and the consistency term: docs/learning.md.
"""
from typing import Dict, Mapping

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from metampc_model.latent_stability import bounded_transition
from metampc_model.normalisation import Normalisation
from metampc_model.nssm_config import NssmConfig, param_shapes

Params = Dict[str, torch.Tensor]


def torch_params(arrays: Mapping[str, np.ndarray], dtype: torch.dtype = torch.float32) -> Params:
    """Parameter arrays (e.g. ``weights_codec.DecodedWeights.params``) as tensors of `dtype`,
    same names, order and shapes; new memory, so the arrays stay as they are."""
    return {name: torch.from_numpy(np.array(value)).to(dtype) for name, value in arrays.items()}


def init_params(config: NssmConfig, seed: int, dtype: torch.dtype = torch.float32) -> Params:
    """Random initial parameters, seeded (the global torch RNG is not touched).

    Every entry is uniform in +-1/sqrt(fan_in) (PyTorch's default for linear layers; for a
    bias the fan-in of its layer): the encoder layers and the matrices A, B, C of the paper.
    With ``stable_latent`` the draw is W and A its bounded image (latent_stability.py).
    """
    gen = torch.Generator().manual_seed(int(seed))
    shapes = param_shapes(config)
    params = {}
    for name, shape in shapes.items():
        weight = name[:-len('bias')] + 'weight' if name.endswith('.bias') else name
        bound = 1.0 / np.sqrt(shapes[weight][-1])
        params[name] = ((torch.rand(shape, generator=gen, dtype=torch.float64) * 2 - 1)
                        * bound).to(dtype)
    if config.stable_latent:
        params['A'] = bounded_transition(params['A'], config.rho_max)
    return params


class Nssm(nn.Module):
    """The NSSM of eq. (SSM) with its configuration and normalisation.

    ``forward(u, y)`` works in normalised units on windows of H + T samples (see the module
    docstring); use it through ``torch.func.functional_call`` with a parameter dict.
    """

    def __init__(self, config: NssmConfig, norm: Normalisation = None, seed: int = 0,
                 dtype: torch.dtype = torch.float32):
        super().__init__()
        config.validate()
        self.config = config
        self.norm = Normalisation.identity(config) if norm is None else norm
        self.norm.validate(config)
        init = init_params(config, seed, dtype)
        self.n_layers = len(config.hidden) + 1
        self.encoder = nn.ModuleList()
        for i in range(self.n_layers):
            layer = nn.Module()
            layer.weight = nn.Parameter(init[f'encoder.{i}.weight'])
            layer.bias = nn.Parameter(init[f'encoder.{i}.bias'])
            self.encoder.append(layer)
        self.A = nn.Parameter(init['A'])
        self.B = nn.Parameter(init['B'])
        self.C = nn.Parameter(init['C'])

    def params(self) -> Params:
        """Detached copies of the module's parameters, canonical order."""
        own = dict(self.named_parameters())
        return {name: own[name].detach().clone() for name in param_shapes(self.config)}

    def encode(self, u_hist: torch.Tensor, y_hist: torch.Tensor) -> torch.Tensor:
        """Eq. (z): (N, H, n_u), (N, H, n_y) normalised -> z_t (N, n_z)."""
        h = torch.cat([u_hist, y_hist], dim=-1).flatten(start_dim=-2)
        for i, layer in enumerate(self.encoder):
            h = F.linear(h, layer.weight, layer.bias)
            if i < self.n_layers - 1:
                h = F.relu(h)
        return h

    def c_powers(self, n: int) -> torch.Tensor:
        """C A^k, k = 0..n, shape (n+1, n_y, n_z)."""
        powers = torch.eye(self.config.n_z, dtype=self.A.dtype,
                           device=self.A.device)[None]            # A^0 .. A^(n-1)
        while powers.shape[0] < n + 1:
            powers = torch.cat([powers, (powers[-1] @ self.A) @ powers], dim=0)
        return self.C @ powers[:n + 1]

    def rollout(self, z: torch.Tensor, u_future: torch.Tensor) -> torch.Tensor:
        """Eqs. (z_next), (haty): z_t (N, n_z), u_{t+1..t+T} (N, T, n_u) -> y_hat (N, T, n_y).

        Computed in closed form, ``y_hat_{t+k} = C A^k z_t + sum_{j=1..k} C A^{k-j} B u_{t+j}``
        (free response plus the Markov parameters convolved with the inputs), which equals the
        step-by-step recursion but costs a few batched products instead of T small ones.
        """
        n_t = u_future.shape[-2]
        c_powers = self.c_powers(n_t)                             # C A^k, k = 0..T
        free = torch.einsum('kyz,...z->...ky', c_powers[1:], z)
        markov = c_powers[:n_t] @ self.B                          # C A^k B, k = 0..T-1
        k = torch.arange(n_t, device=u_future.device)
        lag = k[:, None] - k[None, :]                             # (k, j) -> k - j
        toeplitz = markov[lag.clamp(min=0)] * (lag >= 0)[:, :, None, None].to(markov.dtype)
        return free + torch.einsum('kjyu,...ju->...ky', toeplitz, u_future)

    def consistency(self, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Windows (N, H+T, ...) normalised -> C A^(k-1) rho_{t+1}, k = 1..T (N, T, n_y).

        rho_{t+1} = z_{t+1} - (A z_t + B u_{t+1}), z_t and z_{t+1} from eq. (z) on the
        histories ending at t and t+1 (module docstring, latent consistency).
        """
        n_h = self.config.history
        z_t = self.encode(u[..., :n_h, :], y[..., :n_h, :])
        z_next = self.encode(u[..., 1:n_h + 1, :], y[..., 1:n_h + 1, :])
        rho = z_next - z_t @ self.A.T - u[..., n_h, :] @ self.B.T
        n_t = u.shape[-2] - n_h
        return torch.einsum('kyz,...z->...ky', self.c_powers(n_t - 1), rho)

    def forward(self, u: torch.Tensor, y: torch.Tensor, consistency: bool = False
                ) -> torch.Tensor:
        """Windows (N, H+T, n_u), (N, H+T, n_y) normalised -> y_hat_{t+1..t+T} (N, T, n_y);
        with `consistency`, :meth:`consistency` instead (so that functional_call reaches it)."""
        if consistency:
            return self.consistency(u, y)
        n_h = self.config.history
        return self.rollout(self.encode(u[..., :n_h, :], y[..., :n_h, :]), u[..., n_h:, :])


def prediction_loss(model: Nssm, params: Mapping[str, torch.Tensor], u: torch.Tensor,
                    y: torch.Tensor) -> torch.Tensor:
    """l_SSM of eq. (SSM) averaged over N windows: u (N, H+T, n_u), y (N, H+T, n_y) normalised.

    Returns a scalar: mean over windows and steps of the squared error summed over outputs.
    """
    y_hat = torch.func.functional_call(model, params, (u, y))
    return (y_hat - y[..., model.config.history:, :]).square().sum(dim=-1).mean()


def consistency_loss(model: Nssm, params: Mapping[str, torch.Tensor], u: torch.Tensor,
                     y: torch.Tensor) -> torch.Tensor:
    """l_cons = 1/T sum_{k=1..T} ||C A^(k-1) rho_{t+1}||^2, rho_{t+1} = z_{t+1} - (A z_t +
    B u_{t+1}) (both z from eq. (z)), averaged over N windows (scalar); shapes as l_SSM's."""
    c = torch.func.functional_call(model, params, (u, y), {'consistency': True})
    return c.square().sum(dim=-1).mean()


def training_loss(model: Nssm, params: Mapping[str, torch.Tensor], u: torch.Tensor,
                  y: torch.Tensor) -> torch.Tensor:
    """What training minimises: l_SSM + w l_cons, w = ``consistency_weight`` (w = 0: l_SSM,
    the same computation as :func:`prediction_loss`)."""
    loss = prediction_loss(model, params, u, y)
    weight = model.config.consistency_weight
    return loss + weight * consistency_loss(model, params, u, y) if weight else loss
