"""Classical RK4 over one sample with the input held (zero-order hold), for any plant family.

The kernel works on components (see :mod:`metampc_plant.family`): Python floats for one system
(the plant node: no numpy call overhead) or numpy arrays of shape (B,) for B systems. Both run
the same floating-point operations in the same order, and IEEE-754 +, -, * are correctly
rounded in numpy and in Python alike (neither fuses them), so system b of a batch follows
exactly, bit for bit, the trajectory it follows alone.
"""
from typing import Sequence, Tuple

import numpy as np

from metampc_plant.family import PlantFamily


def rk4_components(family: PlantFamily, x: Sequence, u: Sequence, theta: Sequence, dt: float,
                   substeps: int) -> Tuple:
    """Integrate one sample of dt s by `substeps` RK4 steps with u held.

    Args:
        x: n_x state components (floats or (B,) arrays).
        u: n_u input components.
        theta: n_theta parameter components.

    Returns:
        The n_x state components after dt; overflow gives inf/nan, never an exception.
    """
    h = dt / substeps
    hh = 0.5 * h
    h6 = h / 6.0
    rhs = family.rhs
    x = list(x)     # lists, not tuples of generators: a quarter faster on one system
    for _ in range(substeps):
        k1 = rhs(x, u, theta)
        k2 = rhs([xi + hh * ki for xi, ki in zip(x, k1)], u, theta)
        k3 = rhs([xi + hh * ki for xi, ki in zip(x, k2)], u, theta)
        k4 = rhs([xi + h * ki for xi, ki in zip(x, k3)], u, theta)
        x = [xi + h6 * (a + 2.0 * b + 2.0 * c + d) for xi, a, b, c, d in zip(x, k1, k2, k3, k4)]
    return tuple(x)


def rk4_sample(family: PlantFamily, x: np.ndarray, u: np.ndarray, theta: np.ndarray,
               dt: float, substeps: int) -> np.ndarray:
    """:func:`rk4_components` on stacked arrays.

    Args:
        x: states, shape (B, n_x).
        u: inputs, shape (B, n_u).
        theta: parameters, shape (B, n_theta).

    Returns:
        The states after dt, shape (B, n_x).
    """
    return np.stack(rk4_components(family, x.T, u.T, theta.T, dt, substeps), axis=1)


__all__ = ['rk4_components', 'rk4_sample']
