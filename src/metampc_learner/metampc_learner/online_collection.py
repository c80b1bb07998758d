"""Algorithm 1's online collection: closed-loop source data from the latent MPC, eq. (ub).

After the inner loop of task b (eq. (inner_imaml)) the meta-training core calls the collector with
(task, theta_b, omega_b); it drives the source system theta_b (the plant core) with the
controller's own tick (:class:`~metampc_controller.controller_core.ControllerCore` on the latent
MPC of eq. (mpc), offset-free tracking and fallbacks included, in
:func:`~metampc_controller.closed_loop.run_episode`) for bounded episodes with exploration noise,
u^b = clip(u^b_* + u^b_0, u_min, u_max), u^b_0 ~ N(0, noise_std^2 I), and returns the trajectories
(u^b, y^b) (:class:`~metampc_learner.data.Trajectory`) that the core adds to D_source. An episode
ends at the first sample that leaves the state box (the finite samples before it are returned); a
model the MPC cannot use gives no data. Seeded per (seed, task, call, episode): docs/learner.md.
"""
import dataclasses
from dataclasses import dataclass, field
from typing import List

import numpy as np
import torch

from metampc_common.params import check_fields, param
from metampc_common.excitation import excitation
from metampc_controller.closed_loop import run_episode
from metampc_controller.controller_core import ControllerCore, ModelBundle
from metampc_controller.controller_params import ControllerConfig
from metampc_controller.mpc import MpcConfig, NO_TIME_LIMIT
from metampc_model.nssm import Nssm, Params
from metampc_model.predictor import NssmPredictor
from metampc_learner.data import SourceConfig, Trajectory
from metampc_plant.simulator import Plant


@dataclass
class OnlineCollectionConfig:
    """Settings of the closed-loop collection of Algorithm 1.

    Attributes:
        episodes: episodes per call (per task and outer step).
        episode_samples: closed-loop samples per episode (after the H warm-up samples).
        noise_std: exploration std of eq. (ub), input units (Sigma = noise_std^2 I).
        horizon: N of the MPC, samples.
        q: weight of each of the family's tracked outputs; the others get weight 0.
        r: Delta-u weight of the MPC.
        ref_bound: set-points uniform within +-ref_bound of the family's reference (output
            units).
        ref_hold_s: time each set-point is held, s.
        seed: seed of initial states, warm-up inputs, set-points and noise.
    """

    episodes: int = param(1, 'episodes per task and outer step', ge=1)
    episode_samples: int = param(60, 'closed-loop samples per episode after H warm-up', ge=1)
    noise_std: float = param(0.2, 'exploration std of eq. ub', ge=0)
    horizon: int = param(20, 'MPC horizon N of the collection', ge=1)
    q: float = 1.0
    r: float = param(0.05, 'MPC Delta-u weight of the collection', gt=0)
    ref_bound: float = param(1.0, "set-points uniform within +-b of the family's reference",
                             ge=0)
    ref_hold_s: float = param(2.0, 'set-point hold time, s', gt=0)
    seed: int = 0

    def validate(self) -> None:
        """Raise ValueError naming the first field that is out of range."""
        check_fields(self)
        if not (self.q > 0 and self.seed >= 0):
            raise ValueError('need q > 0 and seed >= 0')


@dataclass
class CollectionStats:
    """Counters over the collector's life.

    Attributes:
        calls: collector calls (one per task and outer step).
        episodes: episodes run.
        samples: samples returned.
        escaped: episodes cut short because the state left the box.
        model_failures: calls without data because the MPC rejected the model.
        mpc_fallbacks: ticks whose answer was a fallback (the MPC's shifted previous plan).
    """

    calls: int = 0
    episodes: int = 0
    samples: int = 0
    escaped: int = 0
    model_failures: int = 0
    mpc_fallbacks: int = 0


@dataclass
class OnlineCollector:
    """Callable ``(task, theta, omega_b) -> [Trajectory]``: the meta-training core's collector.

    Attributes:
        model: the NSSM being meta-trained (architecture and normalisation; its own weights are
            not used).
        config: collection settings.
        source: simulator settings shared with the source set (family, dt, substeps,
            state_bound, excitation with the input bounds).
        stats: counters, updated by every call.
    """

    model: Nssm
    config: OnlineCollectionConfig
    source: SourceConfig
    stats: CollectionStats = field(default_factory=CollectionStats)

    def __post_init__(self):
        self.config.validate()
        self.source = self.source.resolved()
        self.family = self.source.plant_family
        n_y = self.model.config.n_y
        if (n_y, self.model.config.n_u) != (self.family.n_y, self.family.n_u):
            raise ValueError(f'the model has n_y = {n_y}, n_u = {self.model.config.n_u}; family '
                             f'{self.family.name} has {self.family.n_y}, {self.family.n_u}')
        exc = self.source.excitation
        q = np.zeros(n_y)
        q[list(self.family.tracked)] = self.config.q
        # No wall-clock cap: a simulated episode waits for nothing, and a cap that trips on a
        # loaded machine would change the source data of a seeded meta-training.
        self._mpc_config = MpcConfig(horizon=self.config.horizon, q=tuple(q), r=self.config.r,
                                     u_min=exc.u_min, u_max=exc.u_max,
                                     time_limit=NO_TIME_LIMIT)

    def __call__(self, task: int, theta: np.ndarray, params: Params) -> List[Trajectory]:
        """Run `episodes` closed-loop episodes of source system `task` with omega_b = params;
        theta is its parameter vector (n_theta,) (a number: one component)."""
        call = self.stats.calls
        self.stats.calls += 1
        try:
            if not all(bool(torch.isfinite(v).all()) for v in params.values()):
                raise ValueError('weights are not finite')
            predictor = NssmPredictor(self.model.config, self.model.norm, params)
            bundle = ModelBundle.of(predictor, call, 'online_collection', 'adapted',
                                    self._mpc_config, monitor=False)
        except (ValueError, np.linalg.LinAlgError):
            self.stats.model_failures += 1
            return []
        core = ControllerCore(ControllerConfig(
            rate_hz=1.0 / self.source.dt, mpc=self._mpc_config, n_y=self.family.n_y,
            n_u=self.family.n_u))
        core.offer(bundle)
        out = []
        for episode in range(self.config.episodes):
            rng = np.random.default_rng((self.config.seed, task, call, episode))
            traj = self._episode(core, tuple(np.atleast_1d(theta)), rng)
            self.stats.episodes += 1
            if traj is not None:
                self.stats.samples += len(traj)
                out.append(traj)
        return out

    def _episode(self, core: ControllerCore, theta: tuple, rng: np.random.Generator):
        """One bounded episode of `core` on the source system; the finite samples 1..K as a
        Trajectory (None if none). Draws x0, the warm-up's seed, the set-points, the noise."""
        cfg, src, n_h, fam = self.config, self.source, self.model.config.history, self.family
        steps = n_h + cfg.episode_samples
        x0 = tuple(rng.uniform(fam.x0_low, fam.x0_high, fam.n_x))
        plant = Plant(dataclasses.replace(src.plant_config(), theta=theta, x0=x0))
        warmup = excitation(src.excitation, 1, n_h, src.dt, int(rng.integers(2**31)))[0]
        core.set_references(self._reference(steps + cfg.horizon, rng))
        noise = cfg.noise_std * rng.standard_normal((cfg.episode_samples, fam.n_u))
        episode = run_episode(core, plant, steps, theta, x0, warmup, noise)
        self.stats.mpc_fallbacks += sum(tick.fallback for tick in episode.ticks)
        n = len(episode.y) - 1
        if episode.escaped_at is not None:
            self.stats.escaped += 1
            n = episode.escaped_at - 1
        if n == 0:
            return None
        return Trajectory(np.arange(1, n + 1), episode.u[1:n + 1], episode.y[1:n + 1])

    def _reference(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """References r_0..r_{n-1}, shape (n, n_y): piecewise-constant set-points of the
        tracked outputs around the family's reference (untracked outputs: the reference)."""
        cfg, fam = self.config, self.family
        hold = max(1, int(round(cfg.ref_hold_s / self.source.dt)))
        tracked = list(fam.tracked)
        centre = np.asarray(fam.reference)[tracked]
        levels = rng.uniform(centre - cfg.ref_bound, centre + cfg.ref_bound,
                             size=(-(-n // hold), len(tracked)))
        ref = np.tile(np.asarray(fam.reference, dtype=float), (n, 1))
        ref[:, tracked] = np.repeat(levels, hold, axis=0)[:n]
        return ref


__all__ = ['OnlineCollectionConfig', 'CollectionStats', 'OnlineCollector']
