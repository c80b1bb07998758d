"""The proximal inner problem solved in closed form where the model is linear in its head.

Eq. (inner_imaml) with the one-step loss of y = Theta phi (the feature NARX), a ridge regression
with the meta-model's head Theta_bar as prior mean (Bertinetto et al., ICLR 2019; ALPaCA):

    Theta* = (Y'Phi / M + gamma/2 Theta_bar) (Phi'Phi / M + gamma/2 I)^{-1}

Solved as the stacked least squares [Phi / sqrt(M); sqrt(lambda) I] Theta' = [Y / sqrt(M);
gamma/2 / sqrt(lambda) Theta_bar'] by QR, never through Phi'Phi (cond squared: van der Pol's
nearly collinear lags, cond(Phi) ~ 3e5, lost the least-squares fit there). gamma = 0 is least
squares; lambda = max(gamma/2, RIDGE_FLOOR x Phi'Phi/M's mean diagonal) keeps a singular Phi
solvable, with one warning. Differentiable: autograd through it is eq. (outer)'s meta-gradient.
"""
import warnings

import torch

# Relative floor of the regularisation (times the mean diagonal of Phi'Phi / M): directions of
# Phi whose singular value is below sqrt(RIDGE_FLOOR) of the typical one are damped toward zero
# (1e-7: three orders below the lags' collinearity, seven above float64's rounding).
RIDGE_FLOOR = 1e-14
# Condition number above which the Gram matrix counts as singular (exact collinearity, e.g. a
# constant input beside the constant regressor), worth a warning; below it the floor is silent.
COLLINEAR_COND = 1e13


def ridge(phi: torch.Tensor, y: torch.Tensor, prior: torch.Tensor, gamma: float
          ) -> torch.Tensor:
    """Theta* of the module docstring, batched over leading dimensions.

    Args:
        phi: (..., M, n_phi) regressors.
        y: (..., M, n_y) targets.
        prior: (..., n_y, n_phi) Theta_bar (broadcast over the batch).
        gamma: >= 0, the proximal strength in units of the mean loss.

    Returns:
        (..., n_y, n_phi). Never NaN for finite inputs with M >= 1.
    """
    if gamma < 0:
        raise ValueError(f'gamma must be >= 0, got {gamma}')
    m = phi.shape[-2]
    gram = phi.transpose(-1, -2) @ phi / m
    n = gram.shape[-1]
    eye = torch.eye(n, dtype=gram.dtype)
    scale = torch.diagonal(gram, dim1=-2, dim2=-1).mean(-1)[..., None, None].detach()
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))      # Phi = 0: the floor alone
    reg = max(gamma / 2, 0.0) * eye
    if gamma / 2 < RIDGE_FLOOR * float(scale.max()):
        floor = RIDGE_FLOOR * scale * eye
        cond = torch.linalg.cond(gram.detach())
        if torch.any(~torch.isfinite(cond) | (cond > COLLINEAR_COND)):
            warnings.warn('closed-form fit: the regressors are collinear (a constant input, '
                          'too few distinct samples, or features that are linear in the lags '
                          'on these samples); solved as a ridge regression',
                          RuntimeWarning, stacklevel=2)
        reg = torch.maximum(reg, floor)
    root = torch.sqrt(torch.diagonal(reg, dim1=-2, dim2=-1))[..., None]      # (..., n, 1)
    lhs = torch.cat([phi / m ** 0.5, torch.broadcast_to(root * eye, phi.shape[:-2] + (n, n))],
                    dim=-2)
    # gamma > 0 makes root >= sqrt(gamma/2) > 0; gamma = 0 leaves the prior out
    target = (gamma / 2) / root * prior.transpose(-1, -2) if gamma > 0 else \
        torch.zeros_like(root) * prior.transpose(-1, -2)
    rhs = torch.cat([y / m ** 0.5, torch.broadcast_to(target, phi.shape[:-2] + target.shape[-2:])],
                    dim=-2)
    q, r = torch.linalg.qr(lhs)
    sol = torch.linalg.solve_triangular(r, q.transpose(-1, -2) @ rhs, upper=True)
    return sol.transpose(-1, -2)


def mean_loss(phi: torch.Tensor, y: torch.Tensor, head: torch.Tensor) -> torch.Tensor:
    """1/M sum_m ||y_m - head phi_m||^2 (the one-step loss), batched: (...,)."""
    return (y - phi @ head.transpose(-1, -2)).square().sum(-1).mean(-1)


__all__ = ['COLLINEAR_COND', 'RIDGE_FLOOR', 'ridge', 'mean_loss']
