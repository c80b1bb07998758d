"""Stable latent dynamics by construction: ||A||_2 <= rho_max for every weight vector.

The transition A of eq. (z_next) is trained in coordinates W (the entries of the flat training
vector) and used as A = W h(s) / s, s = ||W||_2, h(s) = rho_max tanh(s / rho_max): every singular
value of W is scaled alike, so ||A||_2 < rho_max (= rho_max once tanh rounds to 1) and the spectral
radius with it; the map is smooth where the largest singular value is simple and nearly the
identity for small W, and every method's gradients see it (:func:`bounded_transition`: W (..., n_z,
n_z) -> A of the same shape). Published weights carry A itself; :func:`transition_coordinates` is
the inverse, for training that starts from published weights. Why:
docs/learning.md#stable-latent-dynamics.
"""
import torch

SMALL = 1e-4   # s / rho_max below which tanh(x) / x is taken as 1 - x^2 / 3 (exact to 1e-17)


def bounded_transition(w: torch.Tensor, rho_max: float) -> torch.Tensor:
    """A from W: (..., n_z, n_z) -> same shape, ||A||_2 <= rho_max; differentiable, vmaps."""
    # keepdim: forward-mode AD (Gauss-Newton CG) turns a 0-dim tensor times a Python float
    # into float64 tangents (torch 2.13)
    # the SVD raises on non-finite input; a diverged W must give a non-finite A instead, which
    # the training safeguards catch (a rejected step, a skipped task)
    finite = torch.nan_to_num(w, nan=0.0, posinf=0.0, neginf=0.0)
    x = torch.linalg.matrix_norm(finite, ord=2, keepdim=True) / rho_max
    safe = torch.where(x < SMALL, torch.ones_like(x), x)   # no 0/0 in either branch's grad
    return w * torch.where(x < SMALL, 1 - x.square() / 3, torch.tanh(safe) / safe)


def transition_coordinates(a: torch.Tensor, rho_max: float) -> torch.Tensor:
    """W from A, the inverse of :func:`bounded_transition` (no gradient needed).

    A saturated at the bound (published in float32, its norm rounds to rho_max) maps to a
    W of norm ~9 rho_max, where A no longer depends on it.

    Raises:
        ValueError: ||A||_2 > rho_max beyond rounding (A is not the image of any W).
    """
    norm = torch.linalg.matrix_norm(a.detach().double(), ord=2, keepdim=True)
    ratio = norm / rho_max
    eps = torch.finfo(a.dtype).eps
    if bool((ratio > 1 + eps ** 0.5).any()):
        raise ValueError(f'A has spectral norm {float(norm.max()):.6g} > rho_max = {rho_max}: '
                         'not a model of this stable NSSM (train it with stable_latent off, '
                         'or with a larger rho_max)')
    ratio = ratio.clamp(max=1 - eps)
    safe = torch.where(ratio < SMALL, torch.ones_like(ratio), ratio)
    factor = torch.where(ratio < SMALL, 1 + ratio.square() / 3, torch.atanh(safe) / safe)
    return (a.double() * factor).to(a.dtype)


__all__ = ['bounded_transition', 'transition_coordinates']
