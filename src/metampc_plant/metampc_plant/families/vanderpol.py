"""Van der Pol oscillator with uncertain damping (the paper, section "Van der Pol oscillators").

::

    x1' = x2
    x2' = theta * x2 * (1 - x1**2) - x1 + u,    y = x,
    theta ~ N(0, 1),  |u| <= 1,  dimensionless.

For theta < 0 the limit cycle is unstable and a state outside it escapes to infinity in finite
time: the state box |x|_inf <= 10 flags it.
"""
from dataclasses import dataclass

from metampc_plant.family import PlantFamily, Signal, ThetaComponent


@dataclass(frozen=True)
class VanDerPol(PlantFamily):
    """x2' = theta x2 (1 - x1^2) - x1 + u (see the module docstring)."""

    def rhs(self, x, u, theta):
        x1, x2 = x
        return x2, theta[0] * x2 * (1.0 - x1 * x1) - x1 + u[0]


FAMILY = VanDerPol(
    name='vanderpol',
    title='van der Pol oscillator with uncertain damping (the paper)',
    states=(Signal('x1', '', 'position'), Signal('x2', '', 'velocity')),
    inputs=(Signal('u', '', 'force'),),
    outputs=(Signal('x1', '', 'position'), Signal('x2', '', 'velocity')),
    theta=(ThetaComponent('theta', '', 'damping', 'normal', 0.0, 1.0),),
    u_min=(-1.0,), u_max=(1.0,), state_bound=10.0,
    x0=(0.0, 0.0), x0_low=(-1.0, -1.0), x0_high=(1.0, 1.0), dt=0.1,
    noise_states=(1,), reference=(0.0, 0.0), tracked=(0,))
