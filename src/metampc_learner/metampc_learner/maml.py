"""MAML meta-gradients of one task (paper, sec. Comparison with MAML).

Inner loop, eq. (inner): M plain gradient steps on l_SSM(D_tr; psi) from omega (gamma = 0).

- First-order MAML, eqs. (outer_maml), (appro): the task's gradient is
  grad_psi l_SSM(D_test; psi) at omega_b.
- Unrolled (second-order) MAML: the exact d l_SSM(D_test; omega_b(omega)) / d omega, by
  differentiating through the M inner steps; its memory grows with M (the comparison of
  sec. maml).
"""
from dataclasses import dataclass

import torch
from torch.func import grad, grad_and_value

from metampc_learner.objective import FlatObjective
from metampc_learner.task_gradient import TaskGradient


@dataclass
class FirstOrderMamlTaskGradient:
    """Callable (omega, D_tr, D_test) -> TaskGradient; attributes as ImamlTaskGradient."""

    objective: FlatObjective
    inner_steps: int
    lr_inner: float

    def __call__(self, omega: torch.Tensor, tr_u: torch.Tensor, tr_y: torch.Tensor,
                 te_u: torch.Tensor, te_y: torch.Tensor) -> TaskGradient:
        obj = self.objective
        psi = obj.inner_loop(omega, tr_u, tr_y, self.inner_steps, self.lr_inner, 0.0)
        g, test_loss = grad_and_value(obj.loss)(psi, te_u, te_y)
        return TaskGradient(g, test_loss, torch.full_like(test_loss, float('nan')), psi)


@dataclass
class UnrolledMamlTaskGradient:
    """Callable (omega, D_tr, D_test) -> TaskGradient through the unrolled inner loop."""

    objective: FlatObjective
    inner_steps: int
    lr_inner: float

    def __call__(self, omega: torch.Tensor, tr_u: torch.Tensor, tr_y: torch.Tensor,
                 te_u: torch.Tensor, te_y: torch.Tensor) -> TaskGradient:
        obj = self.objective

        def outer(w):
            psi = obj.inner_loop(w, tr_u, tr_y, self.inner_steps, self.lr_inner, 0.0)
            loss = obj.loss(psi, te_u, te_y)
            return loss, (loss, psi)

        g, (test_loss, psi) = grad(outer, has_aux=True)(omega)
        return TaskGradient(g, test_loss, torch.full_like(test_loss, float('nan')), psi)
