"""Van der Pol oscillator with uncertain damping (paper, section "Van der Pol oscillators").

Continuous dynamics, with theta the unknown damping::

    x1' = x2
    x2' = theta * x2 * (1 - x1**2) - x1 + u
    y   = x

Sampling: the input is held constant (zero-order hold) over each sample of length ``dt`` s and
the state is integrated with ``substeps`` classical RK4 steps. :class:`BatchVdp` steps B
systems with numpy; :class:`VdpPlant` is its single-system twin on Python floats (the plant
node's), equal to a batch of one bit for bit.

Index convention (shared with the NSSM and the MPC): ``y_k`` is measured at time ``k*dt``;
``u_k`` is the input held over ``((k-1)*dt, k*dt]`` that produced it, so a recorded
trajectory pairs ``(u_k, y_k)``. ``step(u)`` applies ``u`` as ``u_{k+1}`` and returns ``y_{k+1}``.

Divergence: for theta < 0 the limit cycle is unstable and a state outside it escapes to
infinity in finite time. The simulators flag a state that is non-finite or leaves the box
``|x|_inf <= state_bound``; a diverged system is frozen at its last finite state.
"""
import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from metampc_common.params import check_fields, param

N_X = 2
N_U = 1
N_Y = 2


@dataclass
class VdpConfig:
    """Configuration of one simulated van der Pol plant.

    Attributes:
        theta: damping, dimensionless.
        dt: sample time, s (> 0).
        substeps: RK4 steps per sample (>= 1). The default 10 stays within 1e-7 of RK45
            (rtol 1e-10) over 20 s at dt = 0.05 s for theta in [-1.5, 2] (test_vanderpol);
            with h**4 scaling that is about 1.5e-6 at dt = 0.1 s (measured: 1.4e-6, theta = 2).
        x0: initial state [x1, x2].
        u_min, u_max: input bounds; inputs are clipped to them.
        process_noise_std: std of a Gaussian added to x2 after each sample (scaled by sqrt(dt)).
        measurement_noise_std: std of a Gaussian added to each output.
        state_bound: the plant is declared diverged when |x|_inf exceeds this.
        seed: seed of the noise generator.
    """

    theta: float = param(0.0, 'van der Pol damping, dimensionless')
    dt: float = param(0.1, 'sample time, s', gt=0)
    substeps: int = param(10, 'RK4 steps per sample', ge=1)
    x0: Tuple[float, float] = param((0.0, 0.0), 'initial state [x1, x2] (inside state_bound)',
                                    length=N_X)
    u_min: float = param(-1.0, 'input lower bound (<= u_max)')
    u_max: float = param(1.0, 'input upper bound (>= u_min)')
    process_noise_std: float = param(0.0, 'std of the noise added to x2 per sample, times '
                                          'sqrt(dt)', ge=0)
    measurement_noise_std: float = param(0.0, 'std of the noise added to each output', ge=0)
    state_bound: float = param(10.0, 'the plant is declared diverged when |x|_inf exceeds this',
                               gt=0)
    seed: int = param(0, 'noise seed', ge=0)

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        check_fields(self)
        if self.u_min > self.u_max:
            raise ValueError(f'need u_min <= u_max, got [{self.u_min}, {self.u_max}]')
        if max(abs(v) for v in self.x0) > self.state_bound:
            raise ValueError(f'x0 {list(self.x0)} lies outside state_bound {self.state_bound}')


def vdp_rhs(x: np.ndarray, u: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """State derivative.

    Args:
        x: states, shape (B, 2).
        u: inputs, shape (B,).
        theta: dampings, shape (B,).

    Returns:
        dx/dt, shape (B, 2).
    """
    x1 = x[:, 0]
    x2 = x[:, 1]
    return np.stack([x2, theta * x2 * (1.0 - x1 * x1) - x1 + u], axis=1)


# The two RK4 kernels below evaluate the same floating-point operations in the same order, so
# a batch of B systems reproduces B single-system runs bit for bit (IEEE-754 +, -, * are
# correctly rounded in numpy and in Python alike, and neither fuses them).

def rk4_sample(x: np.ndarray, u: np.ndarray, theta: np.ndarray, dt: float,
               substeps: int) -> np.ndarray:
    """Integrate one sample of length dt (s) with the input held, by `substeps` RK4 steps.

    Shapes as in :func:`vdp_rhs`; returns the state after dt, shape (B, 2).
    """
    return np.stack(rk4_sample_scalar(x[:, 0], x[:, 1], u, theta, dt, substeps), axis=1)


def rk4_sample_scalar(x1: float, x2: float, u: float, theta: float, dt: float,
                      substeps: int) -> Tuple[float, float]:
    """The RK4 sample of :func:`rk4_sample` on the two state components.

    Written with plain arithmetic only, so it runs on Python floats (one system: about 50x
    faster than numpy at B=1) and on numpy arrays of shape (B,) alike (:func:`rk4_sample`).
    Returns (x1, x2) after dt s; overflow gives inf/nan, never an exception.
    """
    h = dt / substeps
    hh = 0.5 * h
    h6 = h / 6.0
    for _ in range(substeps):
        a1 = x2
        b1 = theta * x2 * (1.0 - x1 * x1) - x1 + u
        p1 = x1 + hh * a1
        p2 = x2 + hh * b1
        a2 = p2
        b2 = theta * p2 * (1.0 - p1 * p1) - p1 + u
        p1 = x1 + hh * a2
        p2 = x2 + hh * b2
        a3 = p2
        b3 = theta * p2 * (1.0 - p1 * p1) - p1 + u
        p1 = x1 + h * a3
        p2 = x2 + h * b3
        a4 = p2
        b4 = theta * p2 * (1.0 - p1 * p1) - p1 + u
        x1 = x1 + h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        x2 = x2 + h6 * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
    return x1, x2


class BatchVdp:
    """B independent van der Pol systems stepped together (vectorised over the batch).

    All systems share dt, substeps, bounds and noise levels; each has its own theta and
    state. One noise generator, seeded by ``config.seed``, serves the whole batch, so a
    batch of size 1 is the single-system simulator. Without noise, system b of a batch
    follows exactly (bit for bit) the trajectory it would follow alone.
    """

    def __init__(self, thetas: Sequence[float], config: VdpConfig,
                 x0: Optional[np.ndarray] = None):
        """Args:
            thetas: dampings, shape (B,).
            config: shared settings (its theta and x0 are ignored here).
            x0: initial states, shape (B, 2); default: config.x0 for every system.
        """
        config.validate()
        self.config = config
        self.rng = np.random.default_rng(config.seed)
        self.reset(thetas, x0)

    @property
    def batch(self) -> int:
        return self.theta.shape[0]

    def reset(self, thetas: Sequence[float], x0: Optional[np.ndarray] = None) -> np.ndarray:
        """Set new dampings and states, clear the divergence flags, return y_0, shape (B, 2)."""
        self.theta = np.asarray(thetas, dtype=float).reshape(-1)
        if not np.all(np.isfinite(self.theta)):
            raise ValueError('thetas must be finite')
        if x0 is None:
            x0 = np.tile(np.asarray(self.config.x0, dtype=float), (self.batch, 1))
        x0 = np.asarray(x0, dtype=float).reshape(self.batch, N_X)
        if not np.all(np.isfinite(x0)):
            raise ValueError('x0 must be finite')
        self.x = x0.copy()
        self.u = np.zeros(self.batch)
        self.diverged = np.abs(self.x).max(axis=1) > self.config.state_bound
        self.step_index = 0
        return self.output()

    def saturate(self, u: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Clip inputs to [u_min, u_max]; return (clipped (B,), was_clipped (B,) bool)."""
        u = np.broadcast_to(np.asarray(u, dtype=float).reshape(-1), (self.batch,))
        clipped = np.clip(u, self.config.u_min, self.config.u_max)
        return clipped, clipped != u

    def step(self, u: np.ndarray) -> np.ndarray:
        """Hold u (shape (B,) or scalar) for one sample; return y_{k+1}, shape (B, 2).

        Non-finite inputs raise ValueError (the node rejects them before this point).
        Diverged systems stay frozen at their last finite state.
        """
        if not np.all(np.isfinite(u)):
            raise ValueError('inputs must be finite')
        u, _ = self.saturate(u)
        cfg = self.config
        with np.errstate(over='ignore', invalid='ignore'):
            x_new = rk4_sample(self.x, u, self.theta, cfg.dt, cfg.substeps)
        if cfg.process_noise_std > 0:
            x_new[:, 1] += cfg.process_noise_std * np.sqrt(cfg.dt) * self.rng.standard_normal(
                self.batch)
        bad = ~np.all(np.isfinite(x_new), axis=1) | (
            np.abs(np.nan_to_num(x_new, nan=np.inf)).max(axis=1) > cfg.state_bound)
        newly = bad & ~self.diverged
        self.diverged = self.diverged | newly
        keep = ~self.diverged
        self.x[keep] = x_new[keep]
        self.u = np.where(keep | newly, u, self.u)
        self.step_index += 1
        return self.output()

    def output(self) -> np.ndarray:
        """y = x plus measurement noise, shape (B, 2)."""
        y = self.x.copy()
        if self.config.measurement_noise_std > 0:
            y += self.config.measurement_noise_std * self.rng.standard_normal(y.shape)
        return y


class VdpPlant:
    """One van der Pol plant, stepped on Python floats.

    The single-system twin of :class:`BatchVdp`: for the same config it draws the same noise
    and returns the same numbers bit for bit as a batch of one (tested), at about a tenth of
    the cost per step, because numpy's per-call overhead dominates at B = 1. The plant node
    steps it once per sample.
    """

    def __init__(self, config: VdpConfig):
        config.validate()
        self.config = config
        self.rng = np.random.default_rng(config.seed)
        # Noise on x2 per sample, as BatchVdp computes it.
        self._process_scale = config.process_noise_std * math.sqrt(config.dt)
        self._theta = float(config.theta)
        self.reset(self._theta, config.x0)

    @property
    def theta(self) -> float:
        return self._theta

    @property
    def x(self) -> np.ndarray:
        """Current state, shape (2,)."""
        return np.array([self._x1, self._x2])

    @property
    def diverged(self) -> bool:
        return self._diverged

    @property
    def step_index(self) -> int:
        return self._step_index

    def reset(self, theta: Optional[float] = None, x0: Optional[Sequence[float]] = None
              ) -> np.ndarray:
        """Reset to (theta, x0); None keeps the current theta / the configured x0. Returns y_0.

        An x0 outside the box ``|x0|_inf <= state_bound`` is accepted and flagged diverged.
        """
        theta = self._theta if theta is None else float(theta)
        x0 = self.config.x0 if x0 is None else x0
        x0 = np.asarray(x0, dtype=float)
        if x0.shape != (N_X,) or not np.all(np.isfinite(x0)):
            raise ValueError(f'x0 must be {N_X} finite numbers, got {x0.tolist()}')
        if not math.isfinite(theta):
            raise ValueError(f'theta must be finite, got {theta}')
        self._theta = theta
        self._x1, self._x2 = float(x0[0]), float(x0[1])
        self._diverged = max(abs(self._x1), abs(self._x2)) > self.config.state_bound
        self._step_index = 0
        return self.output()

    def saturate(self, u: float) -> Tuple[float, bool]:
        """Clip u to [u_min, u_max]; return (clipped, was_clipped). NaN stays NaN."""
        u = float(u)
        clipped = min(max(u, self.config.u_min), self.config.u_max)
        return clipped, clipped != u

    def step(self, u: float) -> np.ndarray:
        """Hold u for one sample, return y_{k+1}, shape (2,).

        Non-finite inputs raise ValueError. A diverged plant stays frozen at its last finite
        state (its step index still advances).
        """
        if not math.isfinite(u):
            raise ValueError(f'inputs must be finite, got {u}')
        u, _ = self.saturate(u)
        cfg = self.config
        x1, x2 = rk4_sample_scalar(self._x1, self._x2, u, self._theta, cfg.dt, cfg.substeps)
        if cfg.process_noise_std > 0:
            x2 += self._process_scale * float(self.rng.standard_normal())
        bad = not (math.isfinite(x1) and math.isfinite(x2)) or max(abs(x1), abs(x2)) > (
            cfg.state_bound)
        self._diverged = self._diverged or bad
        if not self._diverged:
            self._x1, self._x2 = x1, x2
        self._step_index += 1
        return self.output()

    def output(self) -> np.ndarray:
        """y = x plus measurement noise, shape (2,)."""
        if self.config.measurement_noise_std > 0:
            noise = self.config.measurement_noise_std * self.rng.standard_normal(N_Y)
            return np.array([self._x1 + noise[0], self._x2 + noise[1]])
        return np.array([self._x1, self._x2])


def sample_thetas(n: int, rng: np.random.Generator, mean: float = 0.0,
                  std: float = 1.0) -> np.ndarray:
    """Draw n dampings from N(mean, std**2) (the paper's Theta = N(0, 1)); shape (n,)."""
    if std < 0:
        raise ValueError(f'std must be >= 0, got {std}')
    return mean + std * rng.standard_normal(n)


def simulate(thetas: Sequence[float], x0: np.ndarray, u_seq: np.ndarray, config: VdpConfig
             ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulate B systems open loop over K samples.

    Args:
        thetas: shape (B,).
        x0: initial states, shape (B, 2).
        u_seq: inputs u_1..u_K, shape (B, K) (each held over one sample).

    Returns:
        (u, y, valid): u of shape (B, K+1) with u[:, 0] = 0 (no input before the start) and
        u[:, k] the saturated input that produced y[:, k]; y of shape (B, K+1, 2) with
        y[:, 0] = y_0; valid of shape (B, K+1), False from the first diverged sample on.
    """
    sim = BatchVdp(thetas, config, x0)
    u_seq = np.asarray(u_seq, dtype=float)
    n_b, n_k = u_seq.shape
    u = np.zeros((n_b, n_k + 1))
    y = np.zeros((n_b, n_k + 1, N_Y))
    valid = np.ones((n_b, n_k + 1), dtype=bool)
    y[:, 0] = sim.output()
    valid[:, 0] = ~sim.diverged
    for k in range(n_k):
        u[:, k + 1], _ = sim.saturate(u_seq[:, k])
        y[:, k + 1] = sim.step(u_seq[:, k])
        valid[:, k + 1] = ~sim.diverged
    return u, y, valid


__all__ = ['N_X', 'N_U', 'N_Y', 'VdpConfig', 'vdp_rhs', 'rk4_sample',
           'rk4_sample_scalar', 'BatchVdp', 'VdpPlant',
           'sample_thetas', 'simulate']
