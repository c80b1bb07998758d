"""Conjugate gradient for Q x = b with a matrix-free product, eq. (cg).

Solves Q x = P_b, which eq. (gradient) needs, i.e. minimises phi' Q phi / 2 - phi' P_b (the
paper's eq. (cg) omits the 1/2, whose minimiser would be half of it), by a fixed number of CG
steps from phi = 0. No data-dependent branches, so
it runs under ``vmap`` over tasks; divisions by zero (b = 0 or an exact solve) are guarded.
"""
from typing import Callable, Tuple

import torch


def conjugate_gradient(matvec: Callable[[torch.Tensor], torch.Tensor], b: torch.Tensor,
                       steps: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Approximate Q^{-1} b.

    Args:
        matvec: v (P,) -> Q v, Q symmetric (positive definite for convergence).
        b: right-hand side, shape (P,).
        steps: CG iterations.

    Returns:
        x (P,) and the relative residual ||b - Q x|| / ||b|| as CG's recursive residual
        (equal to the true one in exact arithmetic), a scalar tensor.
    """
    tiny = torch.finfo(b.dtype).tiny
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    rr = r @ r
    for _ in range(steps):
        qp = matvec(p)
        pqp = p @ qp
        alpha = torch.where(pqp.abs() > tiny, rr / torch.where(pqp.abs() > tiny, pqp, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * qp
        rr_new = r @ r
        beta = torch.where(rr > tiny, rr_new / torch.where(rr > tiny, rr, 1.0), 0.0)
        p = r + beta * p
        rr = rr_new
    bb = b @ b
    return x, torch.where(bb > tiny, torch.sqrt(rr / torch.where(bb > tiny, bb, 1.0)), 0.0)
