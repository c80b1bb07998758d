"""Steady states of a plant family: the state x_s with f(x_s, u, theta) = 0 at a constant input.

An experiment's set-points can then be outputs that the target can hold: y_s = h(x_s, u, theta)
at input levels inside the bounds (the quadruple tank's equal levels are out of reach for most
of its prior, docs/families.md). scipy's fsolve from the family's operating point; refused
unless the state is finite, inside the state box, and f(x_s) is zero to a tolerance. Pure
numpy / scipy, no rclpy.
"""
from typing import Optional, Sequence

import numpy as np
from scipy.optimize import fsolve

from metampc_plant.family import PlantFamily


def steady_state(family: PlantFamily, theta: Sequence[float], u: Sequence[float],
                 x0: Optional[Sequence[float]] = None, tol: float = 1e-9) -> np.ndarray:
    """x_s (n_x,) with family.rhs(x_s, u, theta) = 0, searched from `x0` (default the family's
    operating point); `u` (n_u,) in the input's units.

    Raises:
        ValueError: u outside the input bounds or of the wrong length, or no steady state found
            (the residual's norm above `tol` times the size of the flows, or x_s outside the
            state box).
    """
    u = np.asarray(u, dtype=float)
    if u.shape != (family.n_u,) or np.any(u < np.asarray(family.u_min)) or np.any(
            u > np.asarray(family.u_max)):
        raise ValueError(f'{family.name}: input {u.tolist()} is not {family.n_u} values inside '
                         f'[{list(family.u_min)}, {list(family.u_max)}]')
    theta = np.asarray(theta, dtype=float)

    def f(x):
        return np.asarray(family.rhs(x, u, theta), dtype=float)

    start = np.asarray(family.x0 if x0 is None else x0, dtype=float)
    x, info, ok, message = fsolve(f, start, full_output=True, xtol=1e-12)
    scale = 1.0 + np.abs(f(start)).max()     # the flows the search started from
    if ok != 1 or not np.all(np.isfinite(x)) or np.abs(f(x)).max() > tol * scale or \
            np.abs(x).max() > family.state_bound:
        raise ValueError(f'{family.name}: no steady state inside the state box |x| <= '
                         f'{family.state_bound} at u = {u.tolist()}, theta = {theta.tolist()} '
                         f'({message.strip()})')
    return x


def steady_output(family: PlantFamily, theta: Sequence[float], u: Sequence[float]) -> np.ndarray:
    """y_s (n_y,) = h(x_s, u, theta) at the steady state of :func:`steady_state`."""
    x = steady_state(family, theta, u)
    return np.asarray(family.output(x, np.asarray(u, dtype=float), np.asarray(theta, float)),
                      dtype=float)


__all__ = ['steady_state', 'steady_output']
