"""iMAML meta-gradient of one task (paper, sec. Solution to the bi-level optimisation problem).

1. Inner loop, eq. (inner_imaml): omega_b = M gradient steps on
   l_SSM(D_tr; psi) + gamma/2 ||psi - omega||^2 from psi = omega.
2. P_b = grad_psi l_SSM(D_test; psi) at omega_b (eq. meta_gradient).
3. Meta-gradient, eqs. (Qb), (gradient): (I + H/gamma)^{-1} P_b, by CG (eq. cg) with
   curvature-vector products at omega_b (exact Hessian or Gauss-Newton, see curvature.py).

Memory does not depend on M: the inner loop keeps no graph.
"""
from dataclasses import dataclass

import torch
from torch.func import grad_and_value

from metampc_learner.cg import conjugate_gradient
from metampc_learner.curvature import curvature_product
from metampc_learner.objective import FlatObjective
from metampc_learner.task_gradient import TaskGradient


@dataclass
class ImamlTaskGradient:
    """Callable (omega, D_tr, D_test) -> TaskGradient, vmappable over tasks.

    Attributes:
        objective: the flat NSSM loss.
        inner_steps: M.
        lr_inner: beta_in, step size of the inner loop.
        gamma: proximal strength (> 0).
        cg_steps: CG iterations.
        curvature: 'gauss_newton' or 'hessian'.
    """

    objective: FlatObjective
    inner_steps: int
    lr_inner: float
    gamma: float
    cg_steps: int
    curvature: str = 'gauss_newton'

    def __call__(self, omega: torch.Tensor, tr_u: torch.Tensor, tr_y: torch.Tensor,
                 te_u: torch.Tensor, te_y: torch.Tensor) -> TaskGradient:
        obj = self.objective
        psi = obj.inner_loop(omega, tr_u, tr_y, self.inner_steps, self.lr_inner, self.gamma)
        p_b, test_loss = grad_and_value(obj.loss)(psi, te_u, te_y)
        curv = curvature_product(self.curvature, obj, psi, tr_u, tr_y)
        meta_grad, residual = conjugate_gradient(lambda v: v + curv(v) / self.gamma, p_b,
                                                 self.cg_steps)
        return TaskGradient(meta_grad, test_loss, residual, psi)
