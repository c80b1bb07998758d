"""Steady-state gain of the latent model, and how far two gains agree.

At rest the latent model of eqs. (z_next), (haty) in physical units (:class:`LatentModel`)
holds ``y_s = C (I - A)^{-1} (B u + e) + d``: its steady-state gain is ``G = C (I - A)^{-1} B``
(n_y, n_u). An MPC with integral action (offset-free, docs/mpc.md) plans its steady state with
the model's gain ``G_m`` and corrects by the estimate: against a plant of gain ``G_p`` it
settles only along directions where ``eig(G_p G_m^+)`` has a positive real part (integral
controllability), slowly where it is small. :func:`agreement` gives those eigenvalues for any
reference gain: the plant's, or a least-squares fit of the model's own samples. Pure numpy.
"""
from typing import Optional, Sequence

import numpy as np

from metampc_model.latent_model import LatentModel


def steady_gain(latent: LatentModel) -> np.ndarray:
    """G = C (I - A)^{-1} B (n_y, n_u), output units per input unit.

    Raises:
        ValueError: I - A is singular (a latent integrator: no finite steady state).
    """
    try:
        return latent.C @ np.linalg.solve(np.eye(latent.n_z) - latent.A, latent.B)
    except np.linalg.LinAlgError:
        raise ValueError('the latent model has a pole at 1: no finite steady-state '
                         'gain') from None


def agreement(reference: np.ndarray, model: np.ndarray,
              rows: Optional[Sequence[int]] = None) -> np.ndarray:
    """eig(G_ref G_m^+) (complex, len(rows)) of two steady-state gains (n_y, n_u) on the output
    rows `rows` (None: all): 1 where they agree, negative where the model's sign is wrong on a
    direction (integral action along it diverges). Restrict to the tracked outputs: an
    output with no steady-state gain (a velocity) gives an eigenvalue ~0 of either sign."""
    rows = list(range(reference.shape[0])) if rows is None else list(rows)
    return np.linalg.eigvals(reference[rows] @ np.linalg.pinv(model[rows]))


__all__ = ['agreement', 'steady_gain']
