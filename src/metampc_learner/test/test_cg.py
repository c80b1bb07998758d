"""conjugate_gradient (eq. (cg)) against a dense solve of an explicit SPD matrix, its residual
against the one recomputed, and a zero right-hand side."""
import torch

from metampc_learner.cg import conjugate_gradient

F64 = torch.float64


def test_conjugate_gradient_on_an_explicit_matrix():
    gen = torch.Generator().manual_seed(0)
    m = torch.randn(6, 6, generator=gen, dtype=F64)
    q = m @ m.T + torch.eye(6, dtype=F64)
    b = torch.randn(6, generator=gen, dtype=F64)
    x, res = conjugate_gradient(lambda v: q @ v, b, 6)
    assert torch.allclose(x, torch.linalg.solve(q, b), atol=1e-9)
    assert float(res) < 1e-8
    x2, res2 = conjugate_gradient(lambda v: q @ v, b, 2)
    assert abs(float(res2) - float((b - q @ x2).norm() / b.norm())) < 1e-10
    x0, res0 = conjugate_gradient(lambda v: q @ v, torch.zeros(6, dtype=F64), 3)
    assert torch.equal(x0, torch.zeros(6, dtype=F64)) and float(res0) == 0.0
