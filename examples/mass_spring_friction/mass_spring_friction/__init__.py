"""A plant family defined outside metampc: a mass on a spring with viscous and Coulomb friction.

::

    p' = v
    v' = (-k p - c v - mu tanh(v / V_S) + f) / m,    y = (p, v),

p in m, v in m/s, f in N; theta = (m, k, mu) with m ~ U(0.5, 2) kg, k ~ U(0.5, 3) N/m,
mu ~ U(0, 0.3) N (Coulomb friction, smoothed over V_S = 0.05 m/s), c = 0.1 N s/m fixed;
|f| <= 2 N, dt = 0.1 s.

It registers itself through the entry-point group ``metampc.plant_families`` in setup.cfg:
``pip install -e examples/mass_spring_friction`` and every metampc node finds it by name,
without a change to metampc (docs/families.md).
"""
from dataclasses import dataclass

import numpy as np

from metampc_plant.family import PlantFamily, Signal, ThetaComponent

VISCOUS = 0.1       # c, N s/m
SLIP_SPEED = 0.05   # V_S, m/s: the width of the smoothed Coulomb friction


@dataclass(frozen=True)
class MassSpringFriction(PlantFamily):
    """v' = (-k p - c v - mu tanh(v / V_S) + f) / m."""

    def rhs(self, x, u, theta):
        p, v = x
        m, k, mu = theta
        return v, (-k * p - VISCOUS * v - mu * np.tanh(v / SLIP_SPEED) + u[0]) / m


FAMILY = MassSpringFriction(
    name='mass_spring_friction',
    title='mass on a spring with viscous and Coulomb friction (out of tree)',
    states=(Signal('p', 'm', 'position'), Signal('v', 'm/s', 'velocity')),
    inputs=(Signal('f', 'N', 'force'),),
    outputs=(Signal('p', 'm', 'position'), Signal('v', 'm/s', 'velocity')),
    theta=(ThetaComponent('m', 'kg', 'mass', 'uniform', 0.5, 2.0),
           ThetaComponent('k', 'N/m', 'stiffness', 'uniform', 0.5, 3.0),
           ThetaComponent('mu', 'N', 'Coulomb friction', 'uniform', 0.0, 0.3)),
    u_min=(-2.0,), u_max=(2.0,), state_bound=20.0,
    x0=(0.0, 0.0), x0_low=(-1.0, -1.0), x0_high=(1.0, 1.0), dt=0.1,
    noise_states=(1,), reference=(0.0, 0.0), tracked=(0,))
