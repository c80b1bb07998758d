"""Duffing oscillator with uncertain damping, stiffness and cubic stiffness.

::

    x1' = x2
    x2' = -delta * x2 - alpha * x1 - beta * x1**3 + u,    y = x,
    delta ~ U(0.05, 0.5),  alpha ~ U(-1, 1),  beta ~ U(0.5, 1.5),  |u| <= 1,  dimensionless.

alpha < 0 gives two wells at x1 = +-sqrt(-alpha / beta) with a hump between them; beta > 0
keeps every state bounded for a bounded input.
"""
from dataclasses import dataclass

from metampc_plant.family import PlantFamily, Signal, ThetaComponent


@dataclass(frozen=True)
class Duffing(PlantFamily):
    """x2' = -delta x2 - alpha x1 - beta x1^3 + u (see the module docstring)."""

    def rhs(self, x, u, theta):
        x1, x2 = x
        delta, alpha, beta = theta
        return x2, -delta * x2 - alpha * x1 - beta * x1 * x1 * x1 + u[0]


FAMILY = Duffing(
    name='duffing',
    title='Duffing oscillator (one or two wells)',
    states=(Signal('x1', '', 'position'), Signal('x2', '', 'velocity')),
    inputs=(Signal('u', '', 'force'),),
    outputs=(Signal('x1', '', 'position'), Signal('x2', '', 'velocity')),
    theta=(ThetaComponent('delta', '', 'damping', 'uniform', 0.05, 0.5),
           ThetaComponent('alpha', '', 'linear stiffness (< 0: two wells)', 'uniform', -1.0, 1.0),
           ThetaComponent('beta', '', 'cubic stiffness', 'uniform', 0.5, 1.5)),
    u_min=(-1.0,), u_max=(1.0,), state_bound=10.0,
    x0=(0.0, 0.0), x0_low=(-1.0, -1.0), x0_high=(1.0, 1.0), dt=0.1,
    noise_states=(1,), reference=(0.0, 0.0), tracked=(0,))
