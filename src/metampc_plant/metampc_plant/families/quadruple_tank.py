"""Johansson's quadruple-tank process: 4 states, 2 inputs, 2 outputs, uncertain valve splits.

K. H. Johansson, IEEE Trans. Control Syst. Technol. 8(3), 2000. Levels h (cm), pumps v (V)::

    h1' = -a1/A1 s(h1) + a3/A1 s(h3) + g1 k1/A1 v1
    h2' = -a2/A2 s(h2) + a4/A2 s(h4) + g2 k2/A2 v2
    h3' = -a3/A3 s(h3) + (1 - g2) k2/A3 v2
    h4' = -a4/A4 s(h4) + (1 - g1) k1/A4 v1,      s(h) = sqrt(2 * 981 * max(h, 0)) cm/s,
    y = 0.5 (h1, h2) V (level sensors, 0.5 V/cm),  0 <= v1, v2 <= 10 V,

theta = (g1, g2) ~ U(0.3, 0.8) each (g1 + g2 < 1: a right-half-plane zero); dt 5 s; state box
|h|_inf <= 100 cm (no overflow model). Constants, operating point and why: docs/families.md.
"""
from dataclasses import dataclass

import numpy as np

from metampc_plant.family import PlantFamily, Signal, SQRT_FLOOR, ThetaComponent

GRAVITY = 981.0                      # cm/s^2
AREA = (28.0, 32.0, 28.0, 32.0)      # A1..A4, cm^2
OUTLET = (0.071, 0.057, 0.071, 0.057)  # a1..a4, cm^2
PUMP = (3.33, 3.35)                  # k1, k2, cm^3/(V s)
SENSOR = 0.5                         # V/cm


def _outflow(h):
    """s(h) = sqrt(2 g max(h, 0)), cm/s (max(h, SQRT_FLOOR)); floats, arrays and CasADi
    symbols."""
    return np.sqrt(2.0 * GRAVITY * np.maximum(h, SQRT_FLOOR))


@dataclass(frozen=True)
class QuadrupleTank(PlantFamily):
    """The quadruple-tank equations (see the module docstring)."""

    def rhs(self, x, u, theta):
        h1, h2, h3, h4 = x
        v1, v2 = u
        g1, g2 = theta
        a1, a2, a3, a4 = OUTLET
        A1, A2, A3, A4 = AREA
        k1, k2 = PUMP
        s1, s2, s3, s4 = _outflow(h1), _outflow(h2), _outflow(h3), _outflow(h4)
        return (-a1 / A1 * s1 + a3 / A1 * s3 + g1 * k1 / A1 * v1,
                -a2 / A2 * s2 + a4 / A2 * s4 + g2 * k2 / A2 * v2,
                -a3 / A3 * s3 + (1.0 - g2) * k2 / A3 * v2,
                -a4 / A4 * s4 + (1.0 - g1) * k1 / A4 * v1)

    def output(self, x, u, theta):
        return SENSOR * x[0], SENSOR * x[1]

    def state_from_output(self, y, x_pred):
        """h1, h2 from the sensors; h3, h4 (not measured) as predicted."""
        return np.array([y[0] / SENSOR, y[1] / SENSOR, x_pred[2], x_pred[3]], dtype=float)


FAMILY = QuadrupleTank(
    name='quadruple_tank',
    title="Johansson's quadruple-tank process (2 pumps, 2 measured levels)",
    states=tuple(Signal(f'h{i}', 'cm', f'level of tank {i}') for i in range(1, 5)),
    inputs=(Signal('v1', 'V', 'pump 1 voltage'), Signal('v2', 'V', 'pump 2 voltage')),
    outputs=(Signal('y1', 'V', 'level sensor of tank 1'),
             Signal('y2', 'V', 'level sensor of tank 2')),
    theta=(ThetaComponent('g1', '', 'valve split of pump 1 to tank 1', 'uniform', 0.3, 0.8),
           ThetaComponent('g2', '', 'valve split of pump 2 to tank 2', 'uniform', 0.3, 0.8)),
    u_min=(0.0, 0.0), u_max=(10.0, 10.0), state_bound=100.0,
    x0=(12.4, 12.7, 1.8, 1.4), x0_low=(5.0, 5.0, 0.5, 0.5), x0_high=(20.0, 20.0, 5.0, 5.0),
    dt=5.0, noise_states=(0, 1, 2, 3), reference=(6.2, 6.35), tracked=(0, 1))
