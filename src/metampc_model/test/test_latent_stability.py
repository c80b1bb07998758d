"""The stable latent parameterisation: ||A||_2 < rho_max for any training weights."""
import pytest
import torch
from torch.func import jvp, vmap

from metampc_model.latent_stability import bounded_transition, transition_coordinates
from metampc_model.nssm_config import NssmConfig

F64 = torch.float64


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize('rho', [0.5, 1.0])
def test_any_weights_map_inside_the_bound(rho):
    gen = torch.Generator().manual_seed(0)
    for scale in (1e-3, 0.1, 1.0, 10.0, 1e3):
        w = scale * torch.randn(50, 5, 5, generator=gen, dtype=F64)
        a = bounded_transition(w, rho)
        bound = rho * (1 + 1e-12)        # tanh rounds to 1 at the largest scales
        assert torch.all(torch.linalg.matrix_norm(a, ord=2) <= bound)
        assert torch.all(torch.linalg.eigvals(a).abs().max(dim=-1).values <= bound)
        # every singular value scaled by tanh(s / rho) rho / s, s the largest one of W
        s = torch.linalg.svdvals(w)
        expect = s * (rho * torch.tanh(s[:, :1] / rho) / s[:, :1])
        torch.testing.assert_close(torch.linalg.svdvals(a), expect, rtol=1e-9, atol=1e-300)


def test_small_weights_pass_nearly_unchanged_and_zero_is_fixed():
    w = 1e-3 * torch.randn(5, 5, generator=_gen(1), dtype=F64)
    s = float(torch.linalg.matrix_norm(w, ord=2))
    rel = float((bounded_transition(w, 1.0) - w).norm() / w.norm())
    assert rel == pytest.approx(s ** 2 / 3, rel=1e-3)          # tanh(s)/s = 1 - s^2/3 + ...
    zero = torch.zeros(3, 3, dtype=F64, requires_grad=True)
    out = bounded_transition(zero, 1.0)
    out.sum().backward()
    assert torch.equal(out, torch.zeros(3, 3, dtype=F64))
    assert torch.equal(zero.grad, torch.ones(3, 3, dtype=F64))   # d A / d W = I at 0


def test_non_finite_weights_give_a_non_finite_a_not_an_error():
    w = torch.randn(2, 3, 3, generator=_gen(2), dtype=F64)
    w[0, 1, 1] = float('nan')
    w[1, 0, 2] = float('inf')
    a = bounded_transition(w, 1.0)
    assert not torch.isfinite(a[0]).all() and not torch.isfinite(a[1]).all()


def test_inverse_round_trip_and_refusal_outside_the_bound():
    w = 2.0 * torch.randn(4, 5, 5, generator=_gen(3), dtype=F64)
    torch.testing.assert_close(transition_coordinates(bounded_transition(w, 0.9), 0.9), w,
                               rtol=1e-8, atol=1e-10)
    a = torch.diag(torch.tensor([1.0, 0.5], dtype=F64))
    with pytest.raises(ValueError, match='spectral norm 1.001 > rho_max = 1.0'):
        transition_coordinates(1.001 * a, 1.0)
    # at the bound (saturated, rounded): a finite W that maps back to A
    w = transition_coordinates(a.float(), 1.0)
    assert torch.all(torch.isfinite(w))
    torch.testing.assert_close(bounded_transition(w, 1.0), a.float())


def test_gradients_and_forward_mode_agree_with_finite_differences():
    w = torch.randn(4, 4, generator=_gen(4), dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: bounded_transition(x, 0.8), (w,))
    assert torch.autograd.gradgradcheck(lambda x: bounded_transition(x, 0.8), (w,))
    # Gauss-Newton CG runs jvp under vmap in float32: the tangent keeps the dtype
    gen = _gen(5)
    w32, v32 = torch.randn(3, 5, 5, generator=gen), torch.randn(3, 5, 5, generator=gen)
    out, tangent = vmap(lambda a, b: jvp(lambda x: bounded_transition(x, 1.0), (a,), (b,)))(
        w32, v32)
    assert out.dtype == tangent.dtype == torch.float32
    eps = 1e-6
    fd = (bounded_transition(w32.double() + eps * v32.double(), 1.0)
          - bounded_transition(w32.double() - eps * v32.double(), 1.0)) / (2 * eps)
    torch.testing.assert_close(tangent.double(), fd, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize('rho', [0.0, -1.0, float('inf'), float('nan')])
def test_rho_max_must_be_positive_and_finite(rho):
    with pytest.raises(ValueError, match=r'rho_max must be (> 0|finite), got'):
        NssmConfig(rho_max=rho).validate()
