"""The nonlinear-regime study: the feature NARX on its planner against the true-model NMPC.

One process, no ROS (``scripts/nonlinear_regime.py``; protocol and figures:
docs/nonlinear.md, docs/studies/2026-12-07-nonlinear-regime.md). Per meta-learning method the
feature NARX (:mod:`metampc_model.feature_narx`) is meta-trained on the family's simulated
source systems (:func:`metampc_learner.data.simulate_source`, seed 0 unless told), then per
test target theta* and data seed: ``target_samples`` samples collected as the experiment does
(one episode from ``collect_x0`` under the random-hold exploration), the closed-form adaptation
(:func:`metampc_learner.narx_learning.adapt`), its held-out l_SSM on 2000 other samples, and
one tracking episode of the paper's reference from ``track_x0`` with the planner that
linearises it each tick (:class:`metampc_controller.local_mpc.LocalLinearMpc`). Beside it: the
least-squares ARX(p) of the same samples on the same planner (a linear model: one QP set-up),
the oracle of the class (the meta-features with the least-squares head of 100 target episodes)
and the true-model NMPC (:class:`metampc_controller.nmpc.Nmpc`, the yardstick; once per
theta*, its episode does not depend on the data seed). The tracking cost is the experiment's:
sum_k ||y_{k+1} - r_{k+1}||^2 over the tracked outputs, r_{k+1} the first reference row of the
tick that answered step k. An episode whose state leaves the family's bound costs inf (an
escape).
"""
from dataclasses import dataclass, field
import math
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from metampc_common.excitation import excitation, ExcitationConfig
from metampc_controller.local_mpc import LocalLinearMpc
from metampc_controller.mpc import MpcConfig
from metampc_controller.nmpc import Nmpc, NmpcConfig
from metampc_controller.references import make_reference
from metampc_learner.data import normalisation_from, SourceConfig, simulate_source
from metampc_learner.narx_learning import (adapt, arx_model, fit_head, heldout_loss,
                                           meta_train, NarxMetaConfig)
from metampc_model.feature_narx import FeatureNarx, NarxShape
from metampc_plant.simulator import Plant, PlantConfig, simulate

Record = Tuple[np.ndarray, np.ndarray]
HELDOUT_SAMPLES = 2000
ORACLE_EPISODES = 100


@dataclass
class RegimeConfig:
    """Attributes:
        family: plant family (registered name).
        thetas: test targets theta* (one value per target for a one-component family).
        data_seeds: seeds of each target's adaptation data (one run per theta* and seed).
        methods: meta-learning methods of the feature NARX ('imaml', 'maml').
        order, features, hidden: the feature NARX's sizes (:class:`NarxShape`).
        meta: meta-training settings (method overridden per method).
        gamma: proximal strength of the adaptation (mean-loss units).
        source_seed, n_systems: the source systems.
        target_samples: adaptation samples per target.
        collect_x0, track_x0: initial states of collection and tracking.
        setpoints, segment: the reference (set-points of the tracked output, s each).
        tracked: tracked output.
        mpc: the planners' tracking problem (horizon, weights, bounds).
    """

    family: str = 'vanderpol'
    thetas: Sequence[float] = (1.0, 1.25, 1.5, 1.75, 2.0)
    data_seeds: Sequence[int] = (0, 1)
    methods: Sequence[str] = ('imaml', 'maml')
    order: int = 2
    features: int = 32
    hidden: Tuple[int, ...] = (64,)
    meta: NarxMetaConfig = field(default_factory=lambda: NarxMetaConfig(iterations=1000,
                                                                         gamma=1e-5))
    gamma: float = 1e-5
    source_seed: int = 0
    n_systems: int = 100
    target_samples: int = 300
    collect_x0: Sequence[float] = (0.5, 0.0)
    track_x0: Sequence[float] = (0.0, 0.0)
    setpoints: Sequence[float] = (0.8, -0.5, 0.3, -0.8)
    segment: float = 7.5
    tracked: int = 0
    mpc: MpcConfig = field(default_factory=lambda: MpcConfig(horizon=20, q=(1.0, 0.0), r=0.05,
                                                             u_min=-1.0, u_max=1.0))


def collect(family: str, theta: Sequence[float], x0: Sequence[float], samples: int,
            seed: int, plant: PlantConfig) -> Record:
    """One open-loop episode under the random-hold exploration of the plant's bounds, as the
    experiment collects D_target: (u (K, n_u), y (K, n_y)), u[k] produced y[k], cut at the
    first diverged sample."""
    exc = ExcitationConfig(u_min=tuple(plant.u_min), u_max=tuple(plant.u_max))
    u_seq = excitation(exc, 1, samples, plant.dt, seed)
    u, y, valid = simulate(np.array([theta], float), np.array([x0], float), u_seq, plant)
    n = int(np.argmin(valid[0])) if not valid[0].all() else len(valid[0])
    return u[0, 1:n], y[0, 1:n]


def track(planner, plant: Plant, theta: Sequence[float], x0: Sequence[float],
          config: RegimeConfig, state_of: Optional[Callable] = None) -> float:
    """The tracking cost of one episode (module docstring); `state_of(u_hist, y_hist)` gives
    the planner's state (None: the planner gets y only, as the NMPC estimates its state)."""
    ref = make_reference('setpoint_sequence', setpoints=tuple(config.setpoints),
                         segment=config.segment, outputs=(config.tracked,),
                         n_y=plant.family.n_y)
    dt, horizon = plant.config.dt, config.mpc.horizon
    y = plant.reset(tuple(theta), tuple(x0))
    n_u = plant.family.n_u
    u = np.zeros(n_u)
    u_hist, y_hist = [np.zeros(n_u)] * config.order, [y] * config.order
    planner.reset()
    steps = int(round(len(config.setpoints) * config.segment / dt))
    cost = 0.0
    for k in range(steps):
        r = ref.evaluate(k * dt, dt, horizon)
        state = None if state_of is None else state_of(np.array(u_hist), np.array(y_hist))
        res = planner.solve(state, u, r, y, k)
        u = np.asarray(res.u, float).copy()
        y = plant.step(u)
        if plant.diverged or not np.all(np.isfinite(y)):
            return math.inf
        u_hist, y_hist = u_hist[1:] + [u], y_hist[1:] + [y]
        cost += float((y[config.tracked] - r[0, config.tracked]) ** 2)
    return cost


def run(config: RegimeConfig, log: Callable[[str], None] = print) -> List[Dict]:
    """Every row of the study (module docstring): one dict per (theta*, data seed, model)
    with the tracking cost, its ratio to the NMPC's, held-out and training losses."""
    torch.manual_seed(0)
    source = SourceConfig(family=config.family, n_systems=config.n_systems,
                          seed=config.source_seed).resolved()
    data = simulate_source(source)
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    fam = source.plant_family
    shape = NarxShape(fam.n_u, fam.n_y, config.order, config.features, tuple(config.hidden))
    systems = [[(t.u, t.y) for t in ts] for ts in data.trajectories if ts]
    metas = {}
    for method in config.methods:
        meta_cfg = NarxMetaConfig(**{**config.meta.__dict__, 'method': method})
        res = meta_train(shape, norm, systems, meta_cfg)
        log(f'meta-trained {method}: D_test loss {np.mean(res.curve[:20]):.2e} -> '
            f'{np.mean(res.curve[-20:]):.2e} in {res.elapsed:.0f} s')
        metas[method] = FeatureNarx(shape, norm, res.params)
    plant_cfg = source.plant_config()
    plant_cfg = PlantConfig(**{**plant_cfg.__dict__, 'u_min': tuple(config.mpc.bounds(1)[0]),
                               'u_max': tuple(config.mpc.bounds(1)[1])})
    plant = Plant(plant_cfg)
    rows = []
    for theta in config.thetas:
        th = tuple(np.atleast_1d(theta).astype(float))
        nmpc = Nmpc(NmpcConfig(**config.mpc.shared(), dt=plant_cfg.dt), fam, th)
        c_nmpc = track(nmpc, plant, th, config.track_x0, config)
        log(f'theta* {th}: NMPC cost {c_nmpc:.3f}')
        oracle_data = [collect(config.family, th, x0, 200, 9000 + i, plant_cfg) for i, x0 in
                       enumerate(np.random.default_rng(77).uniform(-1, 1, (ORACLE_EPISODES,
                                                                            fam.n_x)))]
        for seed in config.data_seeds:
            recs = [collect(config.family, th, config.collect_x0, config.target_samples,
                            seed, plant_cfg)]
            held = [collect(config.family, th, config.collect_x0, HELDOUT_SAMPLES,
                            10_000 + seed, plant_cfg)]
            models = {}
            for method, meta in metas.items():
                ad = adapt(meta, recs, config.gamma)
                models[method] = (ad.model, ad.train_loss, ad.rule)
            models['arx'] = (arx_model(next(iter(metas.values())), recs), ad.arx_loss,
                             'least_squares')
            for method, meta in metas.items():
                models[f'oracle_{method}'] = (fit_head(meta, oracle_data), math.nan, 'oracle')
            for name, (model, train, rule) in models.items():
                planner = LocalLinearMpc(config.mpc, model)
                cost = track(planner, plant, th, config.track_x0, config, model.state)
                row = dict(theta=list(th), seed=seed, model=name, rule=rule, cost=cost,
                           nmpc=c_nmpc, ratio=cost / c_nmpc, train_loss=train,
                           heldout=heldout_loss(model, held, 10),
                           failed_linearisations=planner.failed_linearisations)
                rows.append(row)
                log(f'  seed {seed} {name:>13}: cost {cost:8.3f} ratio {cost / c_nmpc:6.3f} '
                    f'held-out {row["heldout"]:.2e} ({rule})')
    return rows


__all__ = ['RegimeConfig', 'collect', 'track', 'run']
