"""The flat training vector of the NSSM's parameters (eq. SSM), and back.

Every training method (meta-training, inner loops, adaptation, supervised, oracle) steps one
vector (P,); the model reads a parameter dict. With ``stable_latent`` the vector holds W where
the dict holds A = bounded_transition(W) (``metampc_model.latent_stability``).
"""
from typing import Mapping

import numpy as np
import torch

from metampc_model.latent_stability import bounded_transition, transition_coordinates
from metampc_model.nssm import Params
from metampc_model.nssm_config import NssmConfig, param_shapes


class TrainingVector:
    """Round trip between a parameter dict and the flat training vector (P,), differentiable.

    Training keeps the weights as one vector so that CG, the proximal term, Adam and vmap
    over tasks work on plain tensors. The vector holds every parameter as it is, except that
    with ``stable_latent`` it holds W in place of A (``latent_stability.py``): every step of
    every method then keeps ||A||_2 < rho_max. :meth:`unflatten` maps back (differentiably,
    under vmap too) for functional_call; the round trip is exact to float rounding.
    """

    def __init__(self, config: NssmConfig):
        self.config = config
        self.shapes = param_shapes(config)
        self.sizes = [int(np.prod(s)) for s in self.shapes.values()]
        self.size = sum(self.sizes)

    def flatten(self, params: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Published weights -> training vector; ValueError if A is outside the bound."""
        cfg = self.config
        return torch.cat([(transition_coordinates(params[n], cfg.rho_max)
                           if n == 'A' and cfg.stable_latent else params[n]).reshape(-1)
                          for n in self.shapes])

    def unflatten(self, flat: torch.Tensor) -> Params:
        """Training vector (..., P) -> published weights (leading dimensions kept)."""
        chunks = torch.split(flat, self.sizes, dim=-1)
        params = {n: c.reshape(*c.shape[:-1], *s)
                  for (n, s), c in zip(self.shapes.items(), chunks)}
        if self.config.stable_latent:
            params['A'] = bounded_transition(params['A'], self.config.rho_max)
        return params
