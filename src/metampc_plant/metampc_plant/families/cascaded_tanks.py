"""Cascaded tanks with overflow (Schoukens et al. 2016 benchmark): pump voltage in, level out.

Levels x1 (upper), x2 (lower tank) in the sensors' volts, pump voltage v (V)::

    x1' = n1 - r(x1) max(n1, 0),   n1 = k4 v - k1 s(x1)
    x2' = n2 - r(x2) max(n2, 0),   n2 = k2 s(x1) - k3 s(x2) + k5 v r(x1),   y = x2
    s(h) = sqrt(max(h, 0)),   r(h) = clip((h - TOP + RIM) / RIM, 0, 1): overflow at TOP = 10 V

The benchmark's eqs. (1)-(3) and the overflow of Worden et al.'s grey-box model (MSSP 112,
2018), its step spread over a rim of RIM = 0.1 V so that RK4 integrates it. theta = (k1..k5),
each uniform within +-20 % of the grey-box fit to the estimation record's first 768 samples;
0.4 <= v <= 6.5 V (that record's range); dt = 4 s. Why and how: docs/real_data.md.
"""
from dataclasses import dataclass

import numpy as np

from metampc_plant.family import PlantFamily, Signal, SQRT_FLOOR, ThetaComponent

TOP = 10.0      # V, the level sensors' reading of a full tank (the measured y saturates there)
RIM = 0.1       # V, the band below TOP over which a tank's overflow sets in
SPREAD = 0.2    # the prior: each k within +-20 % of the fit
# Where the grey-box fit's search starts, before any data: linearised time constants
# 2 sqrt(x) / k of about 100 s at the estimation record's mean level (5.6 V), the pump's
# inflow balancing the outflow at its mean voltage (2.8 V), a small overflow share.
GUESS = (0.05, 0.05, 0.05, 0.04, 0.01)
# The grey-box fit (identification/) to samples 0..767 of the estimation record,
# `python scripts/cascaded_tanks_baselines.py` (docs/real_data.md): k1..k5 and x(0).
FIT_THETA = (0.05502, 0.02966, 0.03260, 0.04920, 0.01626)
FIT_X0 = (6.904, 5.089)


def _root(h):
    """s(h) = sqrt(max(h, 0)), V^0.5 (max(h, SQRT_FLOOR)); floats, arrays and CasADi
    symbols."""
    return np.sqrt(np.maximum(h, SQRT_FLOOR))


def _rim(h):
    """r(h): 0 below TOP - RIM, 1 at and above TOP, linear between."""
    return np.clip((h - (TOP - RIM)) / RIM, 0.0, 1.0)


@dataclass(frozen=True)
class CascadedTanks(PlantFamily):
    """The cascaded tanks' equations (see the module docstring)."""

    def rhs(self, x, u, theta):
        x1, x2 = x
        k1, k2, k3, k4, k5 = theta
        full1 = _rim(x1)
        net1 = k4 * u[0] - k1 * _root(x1)
        net2 = k2 * _root(x1) - k3 * _root(x2) + k5 * u[0] * full1
        return net1 - full1 * np.maximum(net1, 0.0), net2 - _rim(x2) * np.maximum(net2, 0.0)

    def output(self, x, u, theta):
        return (x[1],)

    def state_from_output(self, y, x_pred):
        """x2 from the sensor; x1 (not measured) as predicted."""
        return np.array([x_pred[0], y[0]], dtype=float)


def _around(name: str, description: str, unit: str, value: float) -> ThetaComponent:
    return ThetaComponent(name, unit, description, 'uniform', round((1 - SPREAD) * value, 6),
                          round((1 + SPREAD) * value, 6))


FAMILY = CascadedTanks(
    name='cascaded_tanks',
    title='cascaded tanks with overflow (Schoukens et al. 2016 benchmark), one pump, lower level',
    states=(Signal('x1', 'V', 'upper tank level (sensor volts)'),
            Signal('x2', 'V', 'lower tank level (sensor volts)')),
    inputs=(Signal('v', 'V', 'pump voltage'),),
    outputs=(Signal('y', 'V', 'lower tank level sensor'),),
    theta=(_around('k1', 'upper tank outflow', 'V^0.5/s', FIT_THETA[0]),
           _around('k2', 'inflow of the lower tank from the upper', 'V^0.5/s', FIT_THETA[1]),
           _around('k3', 'lower tank outflow', 'V^0.5/s', FIT_THETA[2]),
           _around('k4', 'pump gain', '1/s', FIT_THETA[3]),
           _around('k5', 'overflow of the full upper tank into the lower', '1/s',
                   FIT_THETA[4])),
    u_min=(0.4,), u_max=(6.5,), state_bound=20.0,
    x0=FIT_X0, x0_low=(2.0, 2.0), x0_high=(9.0, 9.0), dt=4.0,
    noise_states=(0, 1), reference=(5.5,), tracked=(0,))
