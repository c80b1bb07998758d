"""Data sets of the NSSM: trajectories, (H + T)-sample windows, source and target sets.

A :class:`Trajectory` is a run of consecutive samples ``(step k, u_k, y_k)`` in physical units,
all finite, without gaps (u_k produced y_k); windows of H + T samples are cut from one
trajectory only, so none spans an invalid sample or a gap. Non-finite data never enters: a
simulated episode that leaves the state box is dropped whole and counted. The source set: N_s
simulated systems with theta drawn from the family's Theta, excitation inputs, bounded
episodes, each task's episodes cut in time into D_tr and D_test (no shared sample); the target
set: ~300 samples of one theta. Windows as arrays u (N, H + T, n_u), y (N, H + T, n_y).
Pipeline: docs/learning.md#data-pipeline-datapy.
"""
from collections import deque
import dataclasses
from dataclasses import dataclass, field
from typing import Deque, List, Optional, Sequence, Tuple

import numpy as np
import torch

from metampc_common.params import check_fields, param
from metampc_common.excitation import excitation, ExcitationConfig
from metampc_model.normalisation import Normalisation
from metampc_model.nssm_config import NssmConfig
from metampc_plant.family import PlantFamily
from metampc_plant.registry import DEFAULT, get_family
from metampc_plant.simulator import PlantConfig, simulate


@dataclass
class Trajectory:
    """Consecutive finite samples of one system, physical units.

    Attributes:
        steps: (K,) int64 step indices, each one more than the previous.
        u: (K, n_u) inputs; u[k] produced y[k].
        y: (K, n_y) outputs.
    """

    steps: np.ndarray
    u: np.ndarray
    y: np.ndarray

    def __post_init__(self):
        self.steps = np.asarray(self.steps, dtype=np.int64).reshape(-1)
        n = self.steps.shape[0]
        self.u = np.asarray(self.u, dtype=np.float64).reshape(n, -1)
        self.y = np.asarray(self.y, dtype=np.float64).reshape(n, -1)
        if np.any(np.diff(self.steps) != 1):
            raise ValueError('trajectory steps must be consecutive')
        if not (np.all(np.isfinite(self.u)) and np.all(np.isfinite(self.y))):
            raise ValueError('trajectory has non-finite samples')

    def __len__(self) -> int:
        return self.steps.shape[0]


def samples_in(trajectories: Sequence[Trajectory]) -> int:
    """The samples of all `trajectories`."""
    return sum(len(t) for t in trajectories)


def longest_run(trajectories: Sequence[Trajectory]) -> int:
    """The longest run of consecutive valid samples (the longest trajectory; 0 for none)."""
    return max((len(t) for t in trajectories), default=0)


def trajectories_from_samples(steps: np.ndarray, u: np.ndarray, y: np.ndarray,
                              state_bound: float = np.inf) -> List[Trajectory]:
    """Split buffered samples into trajectories (what the learner node calls on its buffer).

    Args:
        steps: (K,) step indices in arrival order (sorted here; duplicates keep the first).
        u: (K, n_u) or (K,) inputs, physical.
        y: (K, n_y) outputs, physical.
        state_bound: samples with a non-finite value or |y|_inf > state_bound are dropped.

    Returns:
        Trajectories cut at every gap in step indices and every dropped sample.
    """
    steps = np.asarray(steps, dtype=np.int64).reshape(-1)
    if steps.size == 0:
        return []
    u = np.asarray(u, dtype=np.float64).reshape(steps.shape[0], -1)
    y = np.asarray(y, dtype=np.float64).reshape(steps.shape[0], -1)
    steps, first = np.unique(steps, return_index=True)
    u, y = u[first], y[first]
    with np.errstate(invalid='ignore'):
        ok = (np.all(np.isfinite(u), axis=1) & np.all(np.isfinite(y), axis=1)
              & (np.abs(np.nan_to_num(y, nan=np.inf)).max(axis=1, initial=0.0) <= state_bound))
    keep = np.flatnonzero(ok)
    if keep.size == 0:
        return []
    new = np.ones(keep.size, dtype=bool)
    new[1:] = (np.diff(keep) != 1) | (np.diff(steps[keep]) != 1)
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], keep.size)
    return [Trajectory(steps[keep[s:e]], u[keep[s:e]], y[keep[s:e]])
            for s, e in zip(starts, ends)]


def windows(trajectories: Sequence[Trajectory], length: int) -> Tuple[np.ndarray, np.ndarray]:
    """All windows of `length` consecutive samples, each inside one trajectory.

    Returns:
        u (N, length, n_u), y (N, length, n_y), physical units; N may be 0.
    """
    us, ys = [], []
    for traj in trajectories:
        for s in range(len(traj) - length + 1):
            us.append(traj.u[s:s + length])
            ys.append(traj.y[s:s + length])
    if not us:
        n_u = trajectories[0].u.shape[1] if trajectories else 0
        n_y = trajectories[0].y.shape[1] if trajectories else 0
        return np.zeros((0, length, n_u)), np.zeros((0, length, n_y))
    return np.stack(us), np.stack(ys)


def split_by_time(trajectories: Sequence[Trajectory], fraction: float
                  ) -> Tuple[List[Trajectory], List[Trajectory]]:
    """Cut every trajectory after round(fraction * K) samples: (first parts, second parts)."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f'fraction must be in (0, 1), got {fraction}')
    first, second = [], []
    for traj in trajectories:
        cut = int(round(fraction * len(traj)))
        if cut > 0:
            first.append(Trajectory(traj.steps[:cut], traj.u[:cut], traj.y[:cut]))
        if cut < len(traj):
            second.append(Trajectory(traj.steps[cut:], traj.u[cut:], traj.y[cut:]))
    return first, second


def normalisation_from(trajectories: Sequence[Trajectory], y_spread: float = 3.0
                       ) -> Normalisation:
    """Statistics of source data: u_n has unit std, y_n has std 1 / y_spread.

    y_spread = 3 maps +-3 standard deviations of the outputs to +-1, which is the output
    scaling of the calibration (docs/architecture.md) (source outputs have std ~1 per channel).
    """
    u = np.concatenate([t.u for t in trajectories])
    y = np.concatenate([t.y for t in trajectories])
    u_std = u.std(axis=0)
    y_std = y.std(axis=0)
    return Normalisation(u.mean(axis=0), np.where(u_std > 0, u_std, 1.0), y.mean(axis=0),
                         y_spread * np.where(y_std > 0, y_std, 1.0))


@dataclass
class Windows:
    """Normalised training windows: u (N, H+T, n_u), y (N, H+T, n_y) tensors."""

    u: torch.Tensor
    y: torch.Tensor

    @classmethod
    def from_trajectories(cls, trajectories: Sequence[Trajectory], norm: Normalisation,
                          config: NssmConfig, dtype: torch.dtype = torch.float32
                          ) -> 'Windows':
        u, y = windows(trajectories, config.window)
        u_n, y_n = norm.normalise(u.reshape(-1, config.window, config.n_u),
                                  y.reshape(-1, config.window, config.n_y))
        return cls(torch.as_tensor(u_n, dtype=dtype), torch.as_tensor(y_n, dtype=dtype))

    def __len__(self) -> int:
        return self.u.shape[0]


@dataclass
class SourceConfig:
    """Simulated source (and target) systems of one plant family.

    Zeros and empty bounds mean "the family's"; :meth:`resolved` fills them in.

    Attributes:
        family: the plant family (registered name): Theta, equations, x0 box, defaults.
        n_systems: N_s.
        episodes_per_system: bounded episodes simulated per system.
        episode_samples: samples per episode (K; episode length K * dt s).
        dt, substeps: sampling of the simulator, s (dt 0: the family's).
        state_bound: box |x|_inf <= state_bound; an episode leaving it is dropped (0: the
            family's).
        excitation: input signal (within the input bounds; empty bounds: the family's).
        seed: seed of thetas, initial states and inputs.
    """

    family: str = param(DEFAULT, 'plant family of the source systems (registered name; see '
                                 'docs/families.md)')
    n_systems: int = param(100, 'N_s, source systems', ge=1)
    episodes_per_system: int = param(2, 'episodes per system', ge=1)
    episode_samples: int = param(200, 'samples per episode', ge=2)
    dt: float = param(0.0, "sample time, s; must equal the plant's (0: the family's)", ge=0)
    substeps: int = param(10, 'RK4 steps per sample', ge=1)
    state_bound: float = param(0.0, "episodes end when |x|_inf exceeds this; target samples "
                                    "beyond it are dropped (0: the family's)", ge=0)
    excitation: ExcitationConfig = field(default_factory=ExcitationConfig)
    seed: int = param(0, 'seed of the source systems and their data', ge=0)

    @property
    def plant_family(self) -> PlantFamily:
        """The family object (UnknownFamily, a ValueError, if it is not installed)."""
        return get_family(self.family)

    def resolved(self) -> 'SourceConfig':
        """A copy with dt, state_bound and the excitation bounds filled in from the family,
        checked against it (ValueError naming the field)."""
        check_fields(self)
        fam = self.plant_family
        exc = self.excitation
        exc = dataclasses.replace(exc, u_min=tuple(exc.u_min or fam.u_min),
                                  u_max=tuple(exc.u_max or fam.u_max))
        exc.validate()
        out = dataclasses.replace(self, dt=self.dt or fam.dt,
                                  state_bound=self.state_bound or fam.state_bound, excitation=exc)
        # The plant's own checks: bounds per input and within the family's.
        out.plant_config().resolved()
        if max(np.abs(fam.x0_low).max(), np.abs(fam.x0_high).max()) > out.state_bound:
            raise ValueError(f'the initial states of family {fam.name} reach beyond state_bound '
                             f'{out.state_bound}')
        return out

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        self.resolved()

    def plant_config(self) -> PlantConfig:
        """The simulator settings of these systems (bounds: the excitation's)."""
        exc = self.excitation
        return PlantConfig(family=self.family, dt=self.dt, substeps=self.substeps,
                           u_min=tuple(exc.u_min), u_max=tuple(exc.u_max),
                           state_bound=self.state_bound)


def simulate_episodes(thetas: np.ndarray, config: SourceConfig, seed: int
                      ) -> Tuple[List[Optional[Trajectory]], int]:
    """One bounded episode per theta (seeded): (trajectories, None where it escaped; escapes).

    thetas: shape (B, n_theta) (or (B,) for one component); initial states uniform in the
    family's x0 box.

    The trajectory holds samples 1..K (sample 0 has no input that produced it).
    """
    config = config.resolved()
    fam = config.plant_family
    thetas = np.asarray(thetas, dtype=float).reshape(-1, fam.n_theta)
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(fam.x0_low, fam.x0_high, size=(thetas.shape[0], fam.n_x))
    u_seq = excitation(config.excitation, thetas.shape[0], config.episode_samples, config.dt,
                       int(rng.integers(2**31)))
    u, y, valid = simulate(thetas, x0, u_seq, config.plant_config())
    out: List[Optional[Trajectory]] = []
    for b in range(thetas.shape[0]):
        ok = valid[b].all() and np.all(np.isfinite(y[b])) and np.all(np.isfinite(u[b]))
        steps = np.arange(1, config.episode_samples + 1)
        out.append(Trajectory(steps, u[b, 1:], y[b, 1:]) if ok else None)
    return out, sum(t is None for t in out)


@dataclass
class SourceData:
    """Raw source data: thetas (N_s, n_theta), per-system trajectories, count of dropped
    episodes."""

    thetas: np.ndarray
    trajectories: List[List[Trajectory]]
    escaped: int


def simulate_source(config: SourceConfig) -> SourceData:
    """N_s systems with theta ~ Theta, `episodes_per_system` episodes each, escapes dropped."""
    rng = np.random.default_rng(config.seed)
    thetas = config.plant_family.sample_theta(rng, config.n_systems)
    all_thetas = np.repeat(thetas, config.episodes_per_system, axis=0)
    episodes, escaped = simulate_episodes(all_thetas, config, int(rng.integers(2**31)))
    per_system = [[t for t in episodes[i * config.episodes_per_system:
                                       (i + 1) * config.episodes_per_system] if t is not None]
                  for i in range(config.n_systems)]
    return SourceData(thetas, per_system, escaped)


def simulate_target(theta: Sequence[float], config: SourceConfig, n_samples: int = 300,
                    seed: int = 0, max_attempts: int = 20) -> List[Trajectory]:
    """About n_samples samples of the system theta (n_theta values, or one number for a
    one-component family), episodes of config.episode_samples.

    max_attempts episodes are simulated in one batch (seeded); the bounded ones are taken in
    order until n_samples are reached, the last one shortened. RuntimeError if too few stay
    bounded.
    """
    theta = np.atleast_1d(np.asarray(theta, dtype=float))
    episodes, _ = simulate_episodes(np.tile(theta, (max_attempts, 1)), config, seed)
    out: List[Trajectory] = []
    have = 0
    for traj in episodes:
        if have >= n_samples:
            break
        if traj is None:
            continue
        keep = min(len(traj), n_samples - have)
        out.append(Trajectory(traj.steps[:keep], traj.u[:keep], traj.y[:keep]))
        have += keep
    if have < n_samples:
        raise RuntimeError(f'theta={theta.tolist()}: only {have} of {n_samples} bounded samples '
                           f'in {max_attempts} episodes')
    return out


class SourceSet:
    """The tasks of meta-training: per system, D_tr and D_test windows (normalised tensors).

    Systems without a window in D_tr or D_test are left out (``left_out`` lists their index in
    the source data). Data collected during meta-training (Algorithm 1) is added per task with
    :meth:`add`; the collected samples are capped at ``max_collected`` in all, the oldest
    trajectories dropped first (``dropped_samples`` counts them).

    Args:
        data: simulated source data.
        norm: normalisation of the model.
        config: the NSSM (window length H + T).
        train_fraction: share of each episode (in time) that goes to D_tr.
        max_collected: cap of collected samples kept.
        dtype: tensor dtype.
    """

    def __init__(self, data: SourceData, norm: Normalisation, config: NssmConfig,
                 train_fraction: float = 0.5, max_collected: int = 20000,
                 dtype: torch.dtype = torch.float32):
        self.norm = norm
        self.config = config
        self.train_fraction = train_fraction
        self.max_collected = max_collected
        self.dtype = dtype
        self.thetas: List[np.ndarray] = []     # per task: theta, shape (n_theta,)
        self.system_index: List[int] = []
        self.left_out: List[int] = []
        self._base: List[Tuple[Windows, Windows]] = []
        self._collected: Deque[Tuple[int, int, Windows, Windows]] = deque()
        self._tasks: List[Tuple[Windows, Windows]] = []
        self.collected_samples = 0
        self.dropped_samples = 0
        for i, trajs in enumerate(data.trajectories):
            tr, te = self._windows(trajs)
            if len(tr) == 0 or len(te) == 0:
                self.left_out.append(i)
                continue
            self.thetas.append(np.asarray(data.thetas[i], dtype=float))
            self.system_index.append(i)
            self._base.append((tr, te))
        if not self._base:
            raise ValueError('no source system has windows for both D_tr and D_test')
        self._tasks = list(self._base)

    def _windows(self, trajectories: Sequence[Trajectory]) -> Tuple[Windows, Windows]:
        tr, te = split_by_time(trajectories, self.train_fraction)
        return (Windows.from_trajectories(tr, self.norm, self.config, self.dtype),
                Windows.from_trajectories(te, self.norm, self.config, self.dtype))

    def __len__(self) -> int:
        return len(self._base)

    def add(self, task: int, trajectories: Sequence[Trajectory]) -> None:
        """Add collected trajectories of task `task` (split in time like the source)."""
        n = sum(len(t) for t in trajectories)
        if n == 0:
            return
        tr, te = self._windows(trajectories)
        self._collected.append((task, n, tr, te))
        self.collected_samples += n
        while self.collected_samples > self.max_collected:
            _, n_old, _, _ = self._collected.popleft()
            self.collected_samples -= n_old
            self.dropped_samples += n_old
        self._rebuild()

    def _rebuild(self) -> None:
        parts = [([tr], [te]) for tr, te in self._base]
        for task, _, tr, te in self._collected:
            parts[task][0].append(tr)
            parts[task][1].append(te)
        self._tasks = [(Windows(torch.cat([w.u for w in trs]), torch.cat([w.y for w in trs])),
                        Windows(torch.cat([w.u for w in tes]), torch.cat([w.y for w in tes])))
                       for trs, tes in parts]

    def sample(self, tasks: Sequence[int], n_windows: int, rng: np.random.Generator
               ) -> Tuple[Windows, Windows]:
        """n_windows of D_tr and of D_test per task (without replacement where possible).

        Returns:
            (train, test) with u (B, n_windows, H+T, n_u) and y (B, n_windows, H+T, n_y).
        """
        train, test = [], []
        for task in tasks:
            for src, dst in zip(self._tasks[task], (train, test)):
                idx = rng.choice(len(src), size=n_windows, replace=len(src) < n_windows)
                idx = torch.as_tensor(idx)
                dst.append((src.u[idx], src.y[idx]))
        return tuple(Windows(torch.stack([u for u, _ in part]), torch.stack([y for _, y in part]))
                     for part in (train, test))


__all__ = ['Trajectory', 'samples_in', 'longest_run', 'trajectories_from_samples', 'windows',
           'split_by_time', 'normalisation_from', 'Windows', 'SourceConfig', 'simulate_episodes',
           'SourceData', 'simulate_source', 'simulate_target', 'SourceSet']
