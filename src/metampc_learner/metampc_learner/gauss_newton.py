"""Levenberg-Marquardt steps on the proximal objective of eq. (infer).

f(psi) = l_SSM(D; psi) + gamma/2 ||psi - anchor||^2 (``FlatObjective.prox_objective``). One
step solves (G + (gamma + mu) I) d = -grad f(psi) by ``cg_steps`` of CG, G the Gauss-Newton
matrix of l_SSM at psi (``curvature.gauss_newton_product``: products only, never formed),
and takes psi + d when f decreases, dividing the damping mu by :data:`MU_DOWN`; otherwise mu
grows by :data:`MU_UP` and the step is solved again, at most :data:`MAX_TRIES` times (then psi
is kept). mu carries over to the next step. Why: gradient steps on the T-step rollout loss
crawl along its ill-conditioned directions; a least-squares ARX reaches a 10x lower loss in
one solve (docs/learning.md, "The adaptation rule"). Not vmappable (data-dependent loop).
"""
from typing import Tuple

import torch
from torch.func import grad_and_value

from metampc_learner.cg import conjugate_gradient
from metampc_learner.curvature import gauss_newton_product
from metampc_learner.objective import FlatObjective

MU_START = 1e-3     # first damping, normalised units (the loss of a good model is ~1e-4..1e-2)
MU_UP = 4.0         # a rejected step: more damping (shorter, nearer the gradient's direction)
MU_DOWN = 3.0       # an accepted one: less (nearer the Gauss-Newton step)
MU_MIN = 1e-7
MAX_TRIES = 20      # 4^20 ~ 1e12 x mu: a short gradient step by then, which decreases f


def lm_step(objective: FlatObjective, psi: torch.Tensor, anchor: torch.Tensor, u: torch.Tensor,
            y: torch.Tensor, gamma: float, mu: float, cg_steps: int
            ) -> Tuple[torch.Tensor, float, float]:
    """One damped Gauss-Newton step (see the module docstring) from psi (P,).

    Returns (psi, rate, mu): the new psi (unchanged when no trial decreased f), the rate
    1 / (gamma + mu) of the accepted step (the gradient step it tends to where G is small;
    0.0 when none was accepted), and the damping for the next step.
    """
    g, value = grad_and_value(objective.prox_objective)(psi, anchor, u, y, gamma)
    curvature = gauss_newton_product(objective, psi, u, y)
    for _ in range(MAX_TRIES):
        shift = gamma + mu
        step, _ = conjugate_gradient(lambda v: curvature(v) + shift * v, -g, cg_steps)
        candidate = psi + step
        trial = float(objective.prox_objective(candidate, anchor, u, y, gamma))
        if trial < float(value):                            # NaN fails it too
            return candidate, 1.0 / shift, max(mu / MU_DOWN, MU_MIN)
        mu *= MU_UP
    return psi, 0.0, mu


__all__ = ['lm_step', 'MU_START']
