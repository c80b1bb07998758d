"""The NSSM loss as a function of one flat weight vector, and the proximal gradient step.

Shared by the inner loops of iMAML (eq. inner_imaml), MAML (eq. inner, gamma = 0) and
meta-inference (eq. infer): each is M steps of gradient descent on
``l_SSM(D; psi) + gamma/2 ||psi - anchor||^2`` from ``psi = anchor`` (l_SSM plus the
latent consistency term where the NSSM's ``consistency_weight`` is set:
``nssm.training_loss``). Written with
``torch.func.grad`` so that it runs under ``vmap`` over tasks and can be differentiated through
(unrolled MAML) or not (iMAML, first-order MAML, adaptation: no graph is kept).
"""
from typing import Tuple

import torch

from torch.func import grad_and_value

from metampc_model.nssm import Nssm, training_loss
from metampc_learner.training_vector import TrainingVector

ARMIJO_C = 1e-4        # sufficient decrease of the Armijo rule (Nocedal & Wright's choice)
MAX_HALVINGS = 30      # lr / 2^30: below any useful step


class FlatObjective:
    """l_SSM of an NSSM over normalised windows, as a function of flat weights (P,).

    Windows: u (N, H+T, n_u), y (N, H+T, n_y); see ``metampc_model.nssm``.
    """

    def __init__(self, model: Nssm):
        self.model = model
        self.spec = TrainingVector(model.config)

    @property
    def size(self) -> int:
        """P, the number of weights."""
        return self.spec.size

    def predict(self, flat: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The outputs whose squared distances to their targets, summed over everything and
        divided by :meth:`n_terms`, are :meth:`loss` (Gauss-Newton's J is their Jacobian):
        y_hat_{t+1..t+T} (N, T, n_y); with a consistency weight w, sqrt(w) times the
        consistency residuals (targets 0) appended along the steps, (N, 2T, n_y)."""
        params = self.spec.unflatten(flat)
        y_hat = torch.func.functional_call(self.model, params, (u, y))
        weight = self.model.config.consistency_weight
        if not weight:
            return y_hat
        c = torch.func.functional_call(self.model, params, (u, y), {'consistency': True})
        return torch.cat([y_hat, weight ** 0.5 * c], dim=-2)

    def loss(self, flat: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The training loss averaged over the N windows (scalar): l_SSM, plus w l_cons with a
        consistency weight w; see nssm.training_loss."""
        return training_loss(self.model, self.spec.unflatten(flat), u, y)

    def n_terms(self, u: torch.Tensor) -> int:
        """N * T: the loss is the sum of squared residuals divided by this (both terms)."""
        return u.shape[-3] * self.model.config.loss_horizon

    def prox_objective(self, psi: torch.Tensor, anchor: torch.Tensor, u: torch.Tensor,
                       y: torch.Tensor, gamma: float) -> torch.Tensor:
        """l_SSM(D; psi) + gamma/2 ||psi - anchor||^2 (scalar)."""
        return self.loss(psi, u, y) + 0.5 * gamma * (psi - anchor).square().sum()

    def prox_step(self, psi: torch.Tensor, anchor: torch.Tensor, u: torch.Tensor,
                  y: torch.Tensor, rate: torch.Tensor, gamma: float
                  ) -> Tuple[torch.Tensor, torch.Tensor]:
        """One safeguarded gradient step on the proximal objective; returns (psi, rate).

        The step psi - rate * grad is taken unless it increases the objective by more than
        rounding (relative sqrt(eps) of the dtype) or makes it non-finite; then psi is kept and
        rate is halved, for this task only (no branches, so it vmaps). While rate is below
        2 / (largest curvature) every step is taken and this is plain gradient descent; the
        safeguard catches the divergence that a sharp task would otherwise turn into NaN.
        """
        g, value = grad_and_value(self.prox_objective)(psi, anchor, u, y, gamma)
        candidate = psi - rate * g
        slack = torch.finfo(value.dtype).eps ** 0.5 * value.abs()
        ok = self.prox_objective(candidate, anchor, u, y, gamma) <= value + slack
        return torch.where(ok, candidate, psi), torch.where(ok, rate, 0.5 * rate)

    def armijo_step(self, psi: torch.Tensor, anchor: torch.Tensor, u: torch.Tensor,
                    y: torch.Tensor, lr: float, gamma: float) -> Tuple[torch.Tensor, float]:
        """One gradient step on the proximal objective, backtracking from `lr` at every step.

        Takes the largest rate r = lr / 2^j, j = 0..MAX_HALVINGS, with the Armijo decrease
        f(psi - r g) <= f(psi) - ARMIJO_C r ||g||^2; returns (psi, r), or (psi unchanged, 0.0)
        when none decreases f. Unlike :meth:`prox_step` a rejected rate costs no step and the
        next step starts from `lr` again, so the first step already moves the loss. Not
        vmappable (data-dependent loop): adaptation, one task at a time.
        """
        g, value = grad_and_value(self.prox_objective)(psi, anchor, u, y, gamma)
        decrease = ARMIJO_C * float(g.square().sum())
        rate = lr
        for _ in range(MAX_HALVINGS + 1):
            candidate = psi - rate * g
            trial = float(self.prox_objective(candidate, anchor, u, y, gamma))
            if trial <= float(value) - rate * decrease:     # NaN fails it too
                return candidate, rate
            rate *= 0.5
        return psi, 0.0

    def inner_loop(self, omega: torch.Tensor, u: torch.Tensor, y: torch.Tensor, steps: int,
                   lr: float, gamma: float) -> torch.Tensor:
        """Eq. (inner_imaml) (gamma > 0) or eq. (inner) (gamma = 0) by `steps` steps from omega."""
        psi = omega
        rate = torch.tensor(lr, dtype=omega.dtype)
        for _ in range(steps):
            psi, rate = self.prox_step(psi, omega, u, y, rate, gamma)
        return psi
