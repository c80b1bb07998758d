"""The plant-family interface: parameterised plants x' = f(x, u, theta), y = g(x, u, theta).

Pure Python (no rclpy). A family is eq. (sys)'s family of parameterised nonlinear systems: its
dimensions, equations, the distribution Theta, input bounds, a divergence box, a default dt, x0
and reference, names and units. The equations are written on components (``rhs`` -> n_x,
``output`` -> n_y), each a float or a numpy array (B,), so the RK4 of
:mod:`metampc_plant.integrate` batches them; written with operators and numpy functions, the
same code takes CasADi symbols (the NMPC's exact derivatives, ``nmpc_shooting``; math.* or
scipy keeps the derivative-free solver). A frozen dataclass (``dataclasses.replace`` makes a
variant), found by name through :mod:`metampc_plant.registry`. How to write one:
docs/families.md.
"""
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence, Tuple

import numpy as np

DISTRIBUTIONS = ('normal', 'uniform', 'fixed')
SUPPORT_STDS = 4.0     # a normal prior's range: mean +- 4 std (6e-5 of the draws beyond)
# What sqrt(max(h, .)) of an empty tank takes in place of 0: the outflow there is 0 to every
# digit (sqrt(1e-100) = 1e-50), and its derivatives (0 below, through the max) are finite,
# where 0 * sqrt'(0) is NaN: the true-model NMPC differentiates the equations exactly.
SQRT_FLOOR = 1e-100


@dataclass(frozen=True)
class Signal:
    """One named component of a state, input or output vector.

    Attributes:
        name: short name used in plots and logs, e.g. 'x1' or 'h1'.
        unit: SI-style unit, '' when dimensionless, e.g. 'rad', 'cm', 'V'.
        description: a few words, e.g. 'angle from the lower rest position'.
    """

    name: str
    unit: str = ''
    description: str = ''

    def label(self) -> str:
        """'name [unit]' or 'name' for plots."""
        return f'{self.name} [{self.unit}]' if self.unit else self.name


@dataclass(frozen=True)
class ThetaComponent:
    """One component of the uncertain parameter vector and its prior.

    Attributes:
        name, unit, description: as :class:`Signal`.
        distribution: 'normal' (a = mean, b = std), 'uniform' (on [a, b]) or 'fixed' (a).
        a, b: the distribution's two numbers.
    """

    name: str
    unit: str = ''
    description: str = ''
    distribution: str = 'normal'
    a: float = 0.0
    b: float = 1.0

    def __post_init__(self):
        if self.distribution not in DISTRIBUTIONS:
            raise ValueError(f'theta component {self.name}: distribution must be one of '
                             f'{", ".join(DISTRIBUTIONS)}, got {self.distribution!r}')
        if self.distribution == 'normal' and not self.b >= 0:
            raise ValueError(f'theta component {self.name}: std must be >= 0, got {self.b}')
        if self.distribution == 'uniform' and not self.a <= self.b:
            raise ValueError(f'theta component {self.name}: need a <= b, got [{self.a}, '
                             f'{self.b}]')

    @property
    def nominal(self) -> float:
        """The mean of the prior."""
        return 0.5 * (self.a + self.b) if self.distribution == 'uniform' else self.a

    @property
    def support(self) -> Tuple[float, float]:
        """The range of the prior, (low, high): a uniform prior's interval, a fixed value, or
        a normal prior's mean +- SUPPORT_STDS stds (the source systems all but never lie
        beyond: a plant scheduled there runs where the meta-model has seen nothing)."""
        if self.distribution == 'normal':
            return self.a - SUPPORT_STDS * self.b, self.a + SUPPORT_STDS * self.b
        if self.distribution == 'uniform':
            return self.a, self.b
        return self.a, self.a

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n draws, shape (n,). 'normal' draws exactly ``a + b * rng.standard_normal(n)``."""
        if self.distribution == 'normal':
            return self.a + self.b * rng.standard_normal(n)
        if self.distribution == 'uniform':
            return rng.uniform(self.a, self.b, n)
        return np.full(n, float(self.a))

    def describe(self) -> str:
        """'N(0, 1)', 'U(0.5, 1.5)' or '= 9.81'."""
        if self.distribution == 'normal':
            return f'N({self.a:g}, {self.b:g}^2)'
        if self.distribution == 'uniform':
            return f'U({self.a:g}, {self.b:g})'
        return f'= {self.a:g}'


@dataclass(frozen=True)
class PlantFamily(ABC):
    """A family of parameterised plants; subclasses write :meth:`rhs` (and :meth:`output`
    when y is not x).

    Attributes:
        name: the registry name, e.g. 'vanderpol'.
        title: one line for logs and docs.
        states, inputs, outputs: the components of x, u, y.
        theta: the components of theta and their prior Theta.
        u_min, u_max: input bounds, one per input (the plant saturates to them; a deployment
            may narrow them, never widen them).
        state_bound: a system counts as diverged once |x|_inf exceeds it (or x turns
            non-finite).
        x0: default initial state.
        x0_low, x0_high: box of the random initial states of simulated episodes.
        dt: default sample time, s.
        noise_states: the states that process noise enters (e.g. the velocity).
        reference: default set-point per output (ignored for untracked outputs).
        tracked: default tracked outputs (indices).
    """

    name: str
    title: str
    states: Tuple[Signal, ...]
    inputs: Tuple[Signal, ...]
    outputs: Tuple[Signal, ...]
    theta: Tuple[ThetaComponent, ...]
    u_min: Tuple[float, ...]
    u_max: Tuple[float, ...]
    state_bound: float
    x0: Tuple[float, ...]
    x0_low: Tuple[float, ...]
    x0_high: Tuple[float, ...]
    dt: float
    noise_states: Tuple[int, ...]
    reference: Tuple[float, ...]
    tracked: Tuple[int, ...]

    def __post_init__(self):
        n_x, n_u, n_y = self.n_x, self.n_u, self.n_y
        checks = (('u_min', self.u_min, n_u), ('u_max', self.u_max, n_u), ('x0', self.x0, n_x),
                  ('x0_low', self.x0_low, n_x), ('x0_high', self.x0_high, n_x),
                  ('reference', self.reference, n_y))
        for what, values, n in checks:
            if len(values) != n:
                raise ValueError(f'family {self.name}: {what} needs {n} values, got '
                                 f'{len(values)}')
        if any(lo > hi for lo, hi in zip(self.u_min, self.u_max)):
            raise ValueError(f'family {self.name}: need u_min <= u_max')
        if not (self.state_bound > 0 and self.dt > 0 and self.theta):
            raise ValueError(f'family {self.name}: need state_bound > 0, dt > 0 and a theta')
        if any(i not in range(n_x) for i in self.noise_states) or any(
                i not in range(n_y) for i in self.tracked):
            raise ValueError(f'family {self.name}: noise_states / tracked out of range')

    @property
    def n_x(self) -> int:
        return len(self.states)

    @property
    def n_u(self) -> int:
        return len(self.inputs)

    @property
    def n_y(self) -> int:
        return len(self.outputs)

    @property
    def n_theta(self) -> int:
        return len(self.theta)

    @property
    def nominal_theta(self) -> Tuple[float, ...]:
        """The prior mean of each component."""
        return tuple(c.nominal for c in self.theta)

    def sample_theta(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n parameter vectors drawn from Theta, shape (n, n_theta); components drawn in
        order, each as :meth:`ThetaComponent.sample` (a seeded rng gives the same draws)."""
        if n < 0:
            raise ValueError(f'n must be >= 0, got {n}')
        return np.stack([c.sample(rng, n) for c in self.theta], axis=1).reshape(n, self.n_theta)

    def check_theta(self, theta: Sequence[float]) -> Tuple[float, ...]:
        """theta as a tuple of n_theta finite floats; ValueError naming the family if not."""
        values = tuple(float(v) for v in np.asarray(theta, dtype=float).reshape(-1))
        if len(values) != self.n_theta or not all(np.isfinite(values)):
            names = ', '.join(c.name for c in self.theta)
            raise ValueError(f'theta of family {self.name} needs {self.n_theta} finite '
                             f'value(s) ({names}), got {list(values)}')
        return values

    def check_theta_in_support(self, theta: Sequence[float]) -> Tuple[float, ...]:
        """:meth:`check_theta`, and each component within its prior's support
        (:attr:`ThetaComponent.support`): the one range check of a theta given from outside
        (the plant's `theta` parameter, a reset, a schedule row). Sampled source systems are
        not held to it (a normal prior's draws may, rarely, lie beyond)."""
        values = self.check_theta(theta)
        for component, value in zip(self.theta, values):
            low, high = component.support
            if not low <= value <= high:
                raise ValueError(f'{component.name} = {value:g} lies outside the range '
                                 f'[{low:g}, {high:g}] of family {self.name}')
        return values

    @abstractmethod
    def rhs(self, x: Sequence, u: Sequence, theta: Sequence) -> Tuple:
        """dx/dt on components (floats or (B,) arrays); see the module docstring."""

    def output(self, x: Sequence, u: Sequence, theta: Sequence) -> Tuple:
        """y on components; default y = x."""
        return tuple(x)

    def state_from_output(self, y: np.ndarray, x_pred: np.ndarray) -> np.ndarray:
        """The state that a measured y (n_y,) tells, the predicted state x_pred (n_x,) filling
        in what y does not measure: how the true-model NMPC (which knows the equations, not
        the state) tracks the state. Default (y = x): y itself."""
        return np.array(y, dtype=float)


__all__ = ['DISTRIBUTIONS', 'SQRT_FLOOR', 'Signal', 'ThetaComponent', 'PlantFamily']
