"""The proximal inner problem solved in closed form where the model is linear in its head.

Eq. (inner_imaml) with the one-step loss of y = Theta phi (the feature NARX), a ridge regression
with the meta-model's head Theta_bar as prior mean (Bertinetto et al., ICLR 2019; ALPaCA):

    Theta* = (Y'Phi / M + gamma/2 Theta_bar) (Phi'Phi / M + gamma/2 I)^{-1}

Differentiable (torch): autograd through it is the exact meta-gradient of eq. (outer). gamma = 0
is least squares; a singular Phi'Phi (collinear samples, a constant input) is regularised by a
floor of RIDGE_FLOOR times its mean diagonal, with one warning.
"""
import warnings

import torch

# Relative floor of the regularisation (times the mean diagonal of Phi'Phi / M): a Gram matrix
# whose condition number passes 1 / RIDGE_FLOOR is solved as a ridge regression, not inverted.
RIDGE_FLOOR = 1e-10
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
    cross = y.transpose(-1, -2) @ phi / m                     # (..., n_y, n_phi)
    n = gram.shape[-1]
    eye = torch.eye(n, dtype=gram.dtype)
    scale = torch.diagonal(gram, dim1=-2, dim2=-1).mean(-1)[..., None, None].detach()
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
    rhs = cross + (gamma / 2) * prior
    chol = torch.linalg.cholesky(gram + reg)
    return torch.cholesky_solve(rhs.transpose(-1, -2), chol).transpose(-1, -2)


def mean_loss(phi: torch.Tensor, y: torch.Tensor, head: torch.Tensor) -> torch.Tensor:
    """1/M sum_m ||y_m - head phi_m||^2 (the one-step loss), batched: (...,)."""
    return (y - phi @ head.transpose(-1, -2)).square().sum(-1).mean(-1)


__all__ = ['COLLINEAR_COND', 'RIDGE_FLOOR', 'ridge', 'mean_loss']
