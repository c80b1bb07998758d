"""Damped pendulum with uncertain mass, length and friction, torque input.

::

    x1' = x2
    x2' = -(g / l) sin(x1) - b / (m l^2) x2 + u / (m l^2),    y = x,
    m ~ U(0.5, 1.5) kg,  l ~ U(0.5, 1.5) m,  b ~ U(0.05, 0.3) N m s,  g = 9.81 m/s^2,
    |u| <= 3 N m.

x1 is the angle from the lower rest position (rad), x2 the angular rate (rad/s). Set-points
within +-1 rad are held by some targets only (docs/families.md), which is what the family tests.
"""
from dataclasses import dataclass

import numpy as np

from metampc_plant.family import PlantFamily, Signal, ThetaComponent

GRAVITY = 9.81  # m/s^2


@dataclass(frozen=True)
class Pendulum(PlantFamily):
    """x2' = -(g/l) sin x1 - b/(m l^2) x2 + u/(m l^2) (see the module docstring)."""

    def rhs(self, x, u, theta):
        x1, x2 = x
        m, length, b = theta
        inertia = m * length * length
        return x2, -(GRAVITY / length) * np.sin(x1) - (b / inertia) * x2 + u[0] / inertia


FAMILY = Pendulum(
    name='pendulum',
    title='damped pendulum, torque input',
    states=(Signal('angle', 'rad', 'from the lower rest position'),
            Signal('rate', 'rad/s', 'angular rate')),
    inputs=(Signal('torque', 'N m', 'at the pivot'),),
    outputs=(Signal('angle', 'rad', 'from the lower rest position'),
             Signal('rate', 'rad/s', 'angular rate')),
    theta=(ThetaComponent('m', 'kg', 'mass', 'uniform', 0.5, 1.5),
           ThetaComponent('l', 'm', 'length', 'uniform', 0.5, 1.5),
           ThetaComponent('b', 'N m s', 'friction', 'uniform', 0.05, 0.3)),
    u_min=(-3.0,), u_max=(3.0,), state_bound=50.0,
    x0=(0.0, 0.0), x0_low=(-1.0, -1.0), x0_high=(1.0, 1.0), dt=0.05,
    noise_states=(1,), reference=(0.0, 0.0), tracked=(0,))
