"""Simulated plants of any family: sampled, saturated, noisy, with a divergence box.

Eq. (sys) under a zero-order hold of the input over each sample of ``dt`` s, integrated with
``substeps`` RK4 steps (:mod:`metampc_plant.integrate`). :class:`BatchPlant` steps B systems of
one family with numpy (states (B, n_x)); :class:`Plant` is its single-system twin on Python
floats (the plant node's), equal to a batch of one bit for bit. y_k is measured at k dt and u_k
is the input held over ((k-1) dt, k dt] that produced it; ``step(u)`` applies u as u_{k+1}
(saturated to the bounds) and returns y_{k+1}. A non-finite state or one outside
``|x|_inf <= state_bound`` flags the system diverged and freezes it at its last finite state
until reset.
"""
import dataclasses
import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from metampc_common.params import check_fields, param
from metampc_plant.family import PlantFamily
from metampc_plant.integrate import rk4_components, rk4_sample
from metampc_plant.registry import DEFAULT, get_family
from metampc_plant.theta_schedule import ThetaSchedule


@dataclass
class PlantConfig:
    """Configuration of simulated plants of one family.

    Empty lists and zeros mean "the family's default"; :meth:`resolved` fills them in.

    Attributes:
        family: registered family name (``metampc_plant.registry``).
        theta: parameter vector, n_theta values (empty: the family's nominal theta).
        theta_schedule: how theta changes over each episode of a single plant
            (:mod:`metampc_plant.theta_schedule`; flat rows; empty: constant). Batches of
            source systems ignore it.
        dt: sample time, s (0: the family's).
        substeps: RK4 steps per sample (>= 1). For van der Pol the default 10 stays within
            1e-7 of RK45 (rtol 1e-10) over 20 s at dt = 0.05 s for theta in [-1.5, 2], about
            1.5e-6 at dt = 0.1 s (measured: 1.4e-6, theta = 2).
        x0: initial state, n_x values (empty: the family's).
        u_min, u_max: input bounds, n_u values each (empty: the family's); inputs are clipped
            to them; they must lie within the family's bounds.
        process_noise_std: std of a Gaussian added to each of the family's noise states after
            each sample, scaled by sqrt(dt).
        measurement_noise_std: std of a Gaussian added to each output.
        state_bound: the plant is declared diverged when |x|_inf exceeds this (0: the family's).
        seed: seed of the noise generator.
    """

    family: str = param(DEFAULT, 'plant family (registered name; see docs/families.md)')
    theta: Tuple[float, ...] = param((), "parameter vector theta (empty: the family's nominal)",
                                     item=float, scalar=True)
    dt: float = param(0.0, "sample time, s (0: the family's)", ge=0)
    substeps: int = param(10, 'RK4 steps per sample', ge=1)
    theta_schedule: Tuple[float, ...] = param(
        (), 'theta over the plant time of each episode: rows [t_start, t_end, theta...] of a '
            'step (t_end = t_start) or a ramp to theta, s (empty: constant; see '
            'theta_schedule.py)',
        item=float)
    x0: Tuple[float, ...] = param((), "initial state (empty: the family's; inside state_bound)",
                                  item=float)
    u_min: Tuple[float, ...] = param((), "input lower bounds, one per input (empty: the "
                                         "family's; within them)", item=float, scalar=True)
    u_max: Tuple[float, ...] = param((), "input upper bounds, one per input (empty: the "
                                         "family's; within them)", item=float, scalar=True)
    process_noise_std: float = param(0.0, "std of the noise added to the family's noise states "
                                          'per sample, times sqrt(dt)', ge=0, live=True)
    measurement_noise_std: float = param(0.0, 'std of the noise added to each output', ge=0,
                                         live=True)
    state_bound: float = param(0.0, "the plant is declared diverged when |x|_inf exceeds this "
                                    "(0: the family's)", ge=0)
    seed: int = param(0, 'noise seed', ge=0)

    @property
    def plant_family(self) -> PlantFamily:
        """The family object (UnknownFamily, a ValueError, if it is not installed)."""
        return get_family(self.family)

    def resolved(self) -> 'PlantConfig':
        """A copy with every default filled in from the family, checked.

        Raises:
            ValueError: naming the first field that does not fit the family (wrong length,
                a bound outside the family's, x0 outside the state box, ...).
        """
        check_fields(self)
        fam = self.plant_family
        out = dataclasses.replace(
            self, theta=fam.check_theta(self.theta or fam.nominal_theta),
            dt=self.dt or fam.dt, x0=tuple(self.x0 or fam.x0),
            u_min=tuple(self.u_min or fam.u_min), u_max=tuple(self.u_max or fam.u_max),
            state_bound=self.state_bound or fam.state_bound)
        if len(out.x0) != fam.n_x:
            raise ValueError(f'x0 of family {fam.name} needs {fam.n_x} values, got '
                             f'{list(out.x0)}')
        for name, values in (('u_min', out.u_min), ('u_max', out.u_max)):
            if len(values) != fam.n_u:
                raise ValueError(f'{name} of family {fam.name} needs {fam.n_u} value(s), got '
                                 f'{list(values)}')
        if any(lo > hi for lo, hi in zip(out.u_min, out.u_max)):
            raise ValueError(f'need u_min <= u_max, got {list(out.u_min)}, {list(out.u_max)}')
        if any(lo < flo for lo, flo in zip(out.u_min, fam.u_min)) or any(
                hi > fhi for hi, fhi in zip(out.u_max, fam.u_max)):
            raise ValueError(f'input bounds [{list(out.u_min)}, {list(out.u_max)}] lie outside '
                             f'those of family {fam.name}: [{list(fam.u_min)}, '
                             f'{list(fam.u_max)}]')
        if max(abs(v) for v in out.x0) > out.state_bound:
            raise ValueError(f'x0 {list(out.x0)} lies outside state_bound {out.state_bound}')
        ThetaSchedule.parse(out.theta_schedule, fam, out.theta)
        return out

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range (see :meth:`resolved`)."""
        self.resolved()


class BatchPlant:
    """B independent systems of one family stepped together (vectorised over the batch).

    All systems share dt, substeps, bounds and noise levels; each has its own theta and
    state. One noise generator, seeded by ``config.seed``, serves the whole batch, so a
    batch of size 1 is the single-system simulator. Without noise, system b of a batch
    follows exactly (bit for bit) the trajectory it would follow alone.
    """

    def __init__(self, thetas: np.ndarray, config: PlantConfig,
                 x0: Optional[np.ndarray] = None):
        """Args:
            thetas: parameter vectors, shape (B, n_theta) (or (B,) for one component).
            config: shared settings (its theta is ignored here).
            x0: initial states, shape (B, n_x); default: config's x0 for every system.
        """
        self.config = config.resolved()
        self.family = self.config.plant_family
        self.rng = np.random.default_rng(config.seed)
        self._u_min = np.asarray(self.config.u_min)
        self._u_max = np.asarray(self.config.u_max)
        self.reset(thetas, x0)

    @property
    def batch(self) -> int:
        return self.theta.shape[0]

    def reset(self, thetas: np.ndarray, x0: Optional[np.ndarray] = None) -> np.ndarray:
        """New parameters and states, divergence flags cleared; returns y_0, shape (B, n_y)."""
        fam = self.family
        thetas = np.asarray(thetas, dtype=float)
        self.theta = thetas.reshape(-1, fam.n_theta)
        if not np.all(np.isfinite(self.theta)):
            raise ValueError('thetas must be finite')
        if x0 is None:
            x0 = np.tile(np.asarray(self.config.x0, dtype=float), (self.batch, 1))
        x0 = np.asarray(x0, dtype=float).reshape(self.batch, fam.n_x)
        if not np.all(np.isfinite(x0)):
            raise ValueError('x0 must be finite')
        self.x = x0.copy()
        self.u = np.zeros((self.batch, fam.n_u))
        self.diverged = np.abs(self.x).max(axis=1) > self.config.state_bound
        self.step_index = 0
        return self.output()

    def saturate(self, u: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Clip inputs to the bounds: (clipped (B, n_u), was_clipped (B,) bool)."""
        u = np.broadcast_to(np.asarray(u, dtype=float).reshape(-1, self.family.n_u),
                            (self.batch, self.family.n_u))
        clipped = np.clip(u, self._u_min, self._u_max)
        return clipped, np.any(clipped != u, axis=1)

    def step(self, u: np.ndarray) -> np.ndarray:
        """Hold u (shape (B, n_u), (B,) for one input, or one input vector for all) for one
        sample; return y_{k+1}, shape (B, n_y).

        Non-finite inputs raise ValueError (the node rejects them before this point).
        Diverged systems stay frozen at their last finite state.
        """
        if not np.all(np.isfinite(u)):
            raise ValueError('inputs must be finite')
        u, _ = self.saturate(u)
        cfg = self.config
        with np.errstate(over='ignore', invalid='ignore'):
            x_new = rk4_sample(self.family, self.x, u, self.theta, cfg.dt, cfg.substeps)
        noisy = list(self.family.noise_states)
        if cfg.process_noise_std > 0 and noisy:
            x_new[:, noisy] += cfg.process_noise_std * np.sqrt(cfg.dt) * (
                self.rng.standard_normal((self.batch, len(noisy))))
        bad = ~np.all(np.isfinite(x_new), axis=1) | (
            np.abs(np.nan_to_num(x_new, nan=np.inf)).max(axis=1) > cfg.state_bound)
        newly = bad & ~self.diverged
        self.diverged = self.diverged | newly
        keep = ~self.diverged
        self.x[keep] = x_new[keep]
        self.u = np.where((keep | newly)[:, None], u, self.u)
        self.step_index += 1
        return self.output()

    def output(self) -> np.ndarray:
        """y = g(x, u, theta) plus measurement noise, shape (B, n_y)."""
        y = np.stack(self.family.output(self.x.T, self.u.T, self.theta.T), axis=1)
        y = np.array(y, dtype=float).reshape(self.batch, self.family.n_y)
        if self.config.measurement_noise_std > 0:
            y += self.config.measurement_noise_std * self.rng.standard_normal(y.shape)
        return y


class Plant:
    """One plant, stepped on Python floats.

    The single-system twin of :class:`BatchPlant`: for the same config it draws the same noise
    and returns the same numbers bit for bit as a batch of one (tested), at a fraction of the
    cost per step, because numpy's per-call overhead dominates at B = 1. The plant node steps
    it once per sample.
    """

    def __init__(self, config: PlantConfig):
        self.config = config.resolved()
        self.family = self.config.plant_family
        self.rng = np.random.default_rng(config.seed)
        self._process_scale = self.config.process_noise_std * math.sqrt(self.config.dt)
        self._u = (0.0,) * self.family.n_u
        self.reset(self.config.theta, self.config.x0)

    @property
    def theta(self) -> Tuple[float, ...]:
        """theta at the current plant time: the one the next sample is integrated with."""
        return self.schedule.theta_at(self.time) if self.schedule.segments else self._theta

    @property
    def time(self) -> float:
        """Plant time of the episode, s: step index x dt, to the ns (so that a schedule's
        change at 30 s lands at step 600 of dt = 0.05 s, not one later by a rounding error)."""
        return round(self._step_index * self.config.dt, 9)

    @property
    def x(self) -> np.ndarray:
        """Current state, shape (n_x,)."""
        return np.array(self._x)

    @property
    def diverged(self) -> bool:
        return self._diverged

    @property
    def step_index(self) -> int:
        return self._step_index

    def reset(self, theta: Optional[Sequence[float]] = None,
              x0: Optional[Sequence[float]] = None,
              schedule: Optional[Sequence[float]] = None) -> np.ndarray:
        """Reset to (theta, x0, schedule); None keeps the current theta (the episode's start
        value) / the configured x0 / the configured theta_schedule. Returns y_0.

        An x0 outside the box ``|x0|_inf <= state_bound`` is accepted and flagged diverged.
        ValueError for a theta or x0 of the wrong length or not finite, or a schedule that does
        not fit (:meth:`ThetaSchedule.parse`).
        """
        fam = self.family
        theta = self._start_theta if theta is None else fam.check_theta(theta)
        x0 = np.asarray(self.config.x0 if x0 is None else x0, dtype=float)
        if x0.shape != (fam.n_x,) or not np.all(np.isfinite(x0)):
            raise ValueError(f'x0 must be {fam.n_x} finite numbers, got {x0.tolist()}')
        self.schedule = ThetaSchedule.parse(
            self.config.theta_schedule if schedule is None else schedule, fam, theta)
        self._start_theta = self._theta = theta
        self._x = tuple(float(v) for v in x0)
        self._u = (0.0,) * fam.n_u
        self._diverged = max(abs(v) for v in self._x) > self.config.state_bound
        self._step_index = 0
        return self.output()

    def set_noise(self, process_noise_std: float, measurement_noise_std: float) -> None:
        """New noise levels (>= 0, a live parameter change), used from the next step on; the
        noise generator goes on from where it is (it draws only for levels > 0)."""
        self.config = dataclasses.replace(self.config, process_noise_std=process_noise_std,
                                          measurement_noise_std=measurement_noise_std)
        self._process_scale = process_noise_std * math.sqrt(self.config.dt)

    def saturate(self, u: Sequence[float]) -> Tuple[Tuple[float, ...], bool]:
        """Clip u (n_u values) to the bounds; return (clipped, was_clipped). NaN stays NaN."""
        cfg = self.config
        clipped = tuple(min(max(float(v), lo), hi)
                        for v, lo, hi in zip(u, cfg.u_min, cfg.u_max))
        return clipped, any(c != float(v) for c, v in zip(clipped, u))

    def step(self, u: Sequence[float]) -> np.ndarray:
        """Hold u (n_u values) for one sample, return y_{k+1}, shape (n_y,).

        Non-finite inputs or a wrong count raise ValueError. A diverged plant stays frozen at
        its last finite state (its step index still advances).
        """
        u = tuple(float(v) for v in np.atleast_1d(u))
        if len(u) != self.family.n_u or not all(math.isfinite(v) for v in u):
            raise ValueError(f'inputs must be {self.family.n_u} finite numbers, got {list(u)}')
        u, _ = self.saturate(u)
        cfg = self.config
        if self.schedule.segments:
            self._theta = self.schedule.theta_at(self.time)
        with np.errstate(over='ignore', invalid='ignore'):
            x = list(rk4_components(self.family, self._x, u, self._theta, cfg.dt,
                                    cfg.substeps))
        noisy = self.family.noise_states
        if self._process_scale > 0 and noisy:
            for i, e in zip(noisy, self.rng.standard_normal(len(noisy))):
                x[i] += self._process_scale * float(e)
        x = tuple(float(v) for v in x)
        bad = not all(math.isfinite(v) for v in x) or max(abs(v) for v in x) > cfg.state_bound
        if not self._diverged:  # as the batch: the input that diverged it is kept, its x not
            self._u = u
            self._diverged = bad
            if not bad:
                self._x = x
        self._step_index += 1
        return self.output()

    def output(self) -> np.ndarray:
        """y = g(x, u, theta) plus measurement noise, shape (n_y,)."""
        y = np.array([float(v) for v in self.family.output(self._x, self._u, self._theta)])
        if self.config.measurement_noise_std > 0:
            y += self.config.measurement_noise_std * self.rng.standard_normal(self.family.n_y)
        return y


def simulate(thetas: np.ndarray, x0: np.ndarray, u_seq: np.ndarray, config: PlantConfig
             ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulate B systems open loop over K samples.

    Args:
        thetas: shape (B, n_theta) (or (B,) for one component).
        x0: initial states, shape (B, n_x).
        u_seq: inputs u_1..u_K, shape (B, K, n_u) (or (B, K) for one input), each held over
            one sample.

    Returns:
        (u, y, valid): u of shape (B, K+1, n_u) with u[:, 0] = 0 (no input before the start)
        and u[:, k] the saturated input that produced y[:, k]; y of shape (B, K+1, n_y) with
        y[:, 0] = y_0; valid of shape (B, K+1), False from the first diverged sample on.
    """
    sim = BatchPlant(thetas, config, x0)
    fam = sim.family
    u_seq = np.asarray(u_seq, dtype=float)
    n_b, n_k = u_seq.shape[:2]
    u_seq = u_seq.reshape(n_b, n_k, fam.n_u)
    u = np.zeros((n_b, n_k + 1, fam.n_u))
    y = np.zeros((n_b, n_k + 1, fam.n_y))
    valid = np.ones((n_b, n_k + 1), dtype=bool)
    y[:, 0] = sim.output()
    valid[:, 0] = ~sim.diverged
    for k in range(n_k):
        u[:, k + 1], _ = sim.saturate(u_seq[:, k])
        y[:, k + 1] = sim.step(u_seq[:, k])
        valid[:, k + 1] = ~sim.diverged
    return u, y, valid


__all__ = ['PlantConfig', 'BatchPlant', 'Plant', 'simulate']
