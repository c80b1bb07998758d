"""Curvature-vector products of the inner loss at omega_b, for the CG solve of eq. (cg).

Q^b = I + H / gamma (eq. Qb) is never formed; CG needs only products with the curvature:

- 'hessian': the exact Hessian of l_SSM(D_tr; psi), forward-over-reverse
  (``jvp`` of ``grad``). Indefinite for this non-convex loss, so I + H/gamma can be too, and
  CG then stalls (measured, docs/architecture.md 'Calibration').
- 'gauss_newton': G = J' (2 / (N T)) J with J the Jacobian of the N x T x n_y predictions
  (and of the consistency residuals with the NSSM's consistency weight: objective.predict):
  the Hessian without the residual-curvature term, positive semi-definite, so I + G/gamma is
  positive definite for any gamma > 0. One ``vjp`` closure is built at psi and reused; each
  product costs one ``jvp`` and one vector-Jacobian product.
"""
from typing import Callable

import torch
from torch.func import grad, jvp, vjp

from metampc_learner.objective import FlatObjective

CURVATURES = ('gauss_newton', 'hessian')
Product = Callable[[torch.Tensor], torch.Tensor]


def hessian_product(objective: FlatObjective, psi: torch.Tensor, u: torch.Tensor,
                    y: torch.Tensor) -> Product:
    """v (P,) -> H v with H the Hessian of l_SSM(D; .) at psi."""
    def loss_grad(p):
        return grad(objective.loss)(p, u, y)

    return lambda v: jvp(loss_grad, (psi,), (v,))[1]


def gauss_newton_product(objective: FlatObjective, psi: torch.Tensor, u: torch.Tensor,
                         y: torch.Tensor) -> Product:
    """v (P,) -> G v = (2 / (N T)) J'J v, J = d y_hat / d psi at psi (FlatObjective.predict)."""
    def predict(p):
        return objective.predict(p, u, y)

    _, pullback = vjp(predict, psi)
    scale = 2.0 / objective.n_terms(u)
    return lambda v: pullback(jvp(predict, (psi,), (v,))[1] * scale)[0]


def curvature_product(kind: str, objective: FlatObjective, psi: torch.Tensor, u: torch.Tensor,
                      y: torch.Tensor) -> Product:
    """The product of the chosen curvature ('gauss_newton' or 'hessian')."""
    if kind == 'gauss_newton':
        return gauss_newton_product(objective, psi, u, y)
    if kind == 'hessian':
        return hessian_product(objective, psi, u, y)
    raise ValueError(f'unknown curvature {kind!r}; expected one of {CURVATURES}')
