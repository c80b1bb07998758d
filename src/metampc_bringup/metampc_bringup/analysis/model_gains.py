"""Steady-state gain and slowest pole of a learned latent model against the plant it models.

The model's gain ``G_m`` and ``eig(G_p G_m^+)`` are :mod:`metampc_model.steady_gain`'s; the
plant's, ``G_p``, is the central difference of the family's steady outputs around an input u_0
(``steady_state.steady_output``). The slowest pole: max |eig(A)| against the plant's,
linearised at the steady state of u_0 and sampled at dt. Pure numpy / scipy;
scripts/model_gains.py prints them per seed of a run folder (docs/mpc.md, the tank's models).
"""
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.linalg import expm

from metampc_model.latent_model import LatentModel
from metampc_model.steady_gain import agreement, steady_gain
from metampc_plant.family import PlantFamily
from metampc_plant.steady_state import steady_output, steady_state


def plant_gain(family: PlantFamily, theta: Sequence[float], u0: Sequence[float],
               du: float = 1e-3) -> np.ndarray:
    """G_p (n_y, n_u): d y_s / d u at u0, central differences of steps `du` (input units)."""
    u0 = np.asarray(u0, dtype=float)
    cols = []
    for j in range(family.n_u):
        step = np.zeros_like(u0)
        step[j] = du
        cols.append((steady_output(family, theta, u0 + step)
                     - steady_output(family, theta, u0 - step)) / (2.0 * du))
    return np.stack(cols, axis=1)


def plant_poles(family: PlantFamily, theta: Sequence[float], u0: Sequence[float], dt: float,
                dx: float = 1e-6) -> np.ndarray:
    """|eig(expm(J dt))|, largest first: the plant linearised at the steady state of u0
    (Jacobian J of the family's rhs by central differences) and sampled at dt (s)."""
    u0, theta = np.asarray(u0, dtype=float), np.asarray(theta, dtype=float)
    x = steady_state(family, theta, u0)
    jac = np.empty((x.size, x.size))
    for j in range(x.size):
        step = np.zeros_like(x)
        step[j] = dx
        jac[:, j] = (np.asarray(family.rhs(x + step, u0, theta), dtype=float)
                     - np.asarray(family.rhs(x - step, u0, theta), dtype=float)) / (2.0 * dx)
    return np.sort(np.abs(np.linalg.eigvals(expm(jac * dt))))[::-1]


def time_constant(pole: float, dt: float) -> float:
    """-dt / ln|pole| (s): the time constant of a sampled real pole (inf at |pole| >= 1)."""
    return float('inf') if abs(pole) >= 1.0 else -dt / float(np.log(abs(pole)))


@dataclass
class GainComparison:
    """A model against the plant at one input.

    Attributes:
        model_gain, plant_gain: G_m, G_p (n_y, n_u).
        ratio_eigs: eig(G_p G_m^+) (complex, n_y): 1 where the model's gain is right, small
            where it is too large, negative where its sign is wrong.
        model_pole, plant_pole: the slowest |pole| of each, sampled at dt.
    """

    model_gain: np.ndarray
    plant_gain: np.ndarray
    ratio_eigs: np.ndarray
    model_pole: float
    plant_pole: float


def compare(latent: LatentModel, family: PlantFamily, theta: Sequence[float],
            u0: Sequence[float], dt: float) -> GainComparison:
    """:class:`GainComparison` of `latent` and the family's plant at theta and u0."""
    g_m, g_p = steady_gain(latent), plant_gain(family, theta, u0)
    return GainComparison(g_m, g_p, agreement(g_p, g_m),
                          float(np.max(np.abs(np.linalg.eigvals(latent.A)))),
                          float(plant_poles(family, theta, u0, dt)[0]))


__all__ = ['compare', 'GainComparison', 'plant_gain', 'plant_poles',
           'time_constant']
