"""The nonlinear-regime study: the feature NARX on its planner against the true-model NMPC.

One process, no ROS (``scripts/nonlinear_regime.py``). Everything comes from the family's
experiment configuration (controller tuning and reference, the excitation that collects
D_target, source systems, x0, tracked outputs, run length). Per method the feature NARX is
meta-trained once (the first seed's source systems), then per target: adapted to
``target_samples`` samples (a share of them collected in closed loop by the model adapted to
the rest: ``closed_loop``), scored on HELDOUT_SAMPLES others, flown by the locally linear MPC
beside the ARX(p) of the same collection and the class's oracle; the yardstick is the
experiment's own NMPC (:func:`~metampc_bringup.analysis.retrack.fly`), the cost the
experiment's (sum of squared tracking errors; an escape costs inf). Protocol: docs/nonlinear.md.
"""
from dataclasses import dataclass, field, replace
from functools import partial
import hashlib
import json
import math
import os
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from metampc_bringup.analysis.paired_stats import format_claim, paired_claim
from metampc_bringup.analysis.retrack import fly, plant_config
from metampc_bringup.experiment_config import ExperimentConfig, load
from metampc_common.excitation import excitation, ExcitationConfig
from metampc_controller.local_mpc import LocalLinearMpc
from metampc_controller.references import make_reference
from metampc_learner.data import normalisation_from, simulate_source
from metampc_learner.narx_learning import (adapt, arx_model, heldout_loss, meta_train,
                                           NarxMetaConfig, one_step_loss)
from metampc_model.feature_narx import FeatureNarx, NarxShape
from metampc_plant.simulator import Plant, PlantConfig, simulate

Record = Tuple[np.ndarray, np.ndarray]
HELDOUT_SAMPLES = 2000
ORACLE_EPISODES = 100
ORACLE_SAMPLES = 200        # per episode
HELDOUT_HORIZON = 10


@dataclass
class RegimeConfig:
    """Attributes:
        experiment: the experiment configuration file (None: config/default.yaml's settings).
        thetas: test targets theta* (each a row of n_theta values); empty: each seed's draw.
        seeds: test seeds (with thetas: the data seeds of every target).
        methods: meta-learning methods of the feature NARX ('imaml', 'maml').
        order: p, the lags (None: the experiment's learner ``narx_order``, the family's).
        features, hidden: the feature NARX's other sizes (:class:`NarxShape`).
        meta: meta-training settings (method overridden per method; its gamma is the
            adaptation's too).
        oracle: also fly the oracle of each method's features.
        overrides: configuration keys set on top of the file's; a value for a section
            ('learner', 'controller', 'plant') is merged into it (a declared regime's
            reference, for example).
        closed_loop: the share of the target's samples collected in closed loop
            (:func:`closed_loop_record`) with the model adapted to the rest (collected open
            loop first); every model is then adapted again on all of them. 0: all open loop.
        exploration: the closed-loop part's exploration, the excitation's band (its
            amplitude) around zero added to the planner's input.
        toward_arx: the adaptation's rule where its fit toward the meta-model loses to the
            ARX on the samples (:func:`~metampc_learner.narx_learning.adapt`): a fit toward
            the ARX's head (True, the learner's) or the ARX's head itself.
    """

    experiment: Optional[str] = None
    thetas: Sequence[Sequence[float]] = ()
    seeds: Sequence[int] = (0, 1)
    methods: Sequence[str] = ('imaml',)
    order: Optional[int] = None
    features: int = 32
    hidden: Tuple[int, ...] = (64,)
    meta: NarxMetaConfig = field(default_factory=NarxMetaConfig)
    oracle: bool = True
    overrides: Dict[str, Any] = field(default_factory=dict)
    closed_loop: float = 0.0
    exploration: float = 0.0
    toward_arx: bool = True

    def __post_init__(self):
        if not 0.0 <= self.closed_loop < 1.0 or not 0.0 <= self.exploration <= 1.0:
            raise ValueError(f'closed_loop must be in [0, 1) and exploration in [0, 1], got '
                             f'{self.closed_loop}, {self.exploration}')


def experiment(config: RegimeConfig, theta: Optional[Sequence[float]] = None
               ) -> ExperimentConfig:
    """The experiment configuration with the study's overrides (and theta* when given)."""
    base = load(config.experiment)
    merged = {key: ({**getattr(base, key), **value} if isinstance(value, dict) else value)
              for key, value in config.overrides.items()}
    if theta is not None:
        merged['theta'] = [float(v) for v in theta]
    return load(config.experiment, merged)


def collect(excitation_config: ExcitationConfig, plant: PlantConfig, theta: Sequence[float],
            x0: Sequence[float], samples: int, seed: int) -> Record:
    """One open-loop episode under `excitation_config` (seeded), as the experiment collects
    D_target: (u (K, n_u), y (K, n_y)), u[k] produced y[k], cut before a diverged sample."""
    u_seq = excitation(excitation_config, 1, samples, plant.dt, seed)
    u, y, valid = simulate(np.array([theta], float), np.array([x0], float), u_seq, plant)
    n = len(valid[0]) if valid[0].all() else int(np.argmin(valid[0]))
    return u[0, 1:n], y[0, 1:n]


def episode(planner, plant: PlantConfig, theta: Sequence[float], x0: Sequence[float],
            reference, steps: int, tracked: Sequence[int],
            state_of: Optional[Callable] = None, lags: int = 1,
            explore: Optional[np.ndarray] = None,
            times: Optional[List[float]] = None) -> Tuple[float, Record]:
    """One closed-loop episode: (its tracking cost, the record (u (K, n_u), y (K, n_y)), u[k]
    produced y[k]). `reference` evaluates the planner's (N, n_y) rows; `state_of(u_hist,
    y_hist)` gives the planner's state from the last `lags` inputs and outputs (None: the
    planner gets y only, as the NMPC estimates x); `explore` (steps, n_u), when given, is added
    to the planner's input before the bounds clip it; `times`, where given, gets each
    planner.solve's wall time (s) appended (the benchmarks' planner timing). An escape: cost
    inf, the record cut before it."""
    sim = Plant(plant)
    y = sim.reset(tuple(theta), tuple(x0))
    n_u, dt, n = sim.family.n_u, plant.dt, planner.config.horizon
    u = np.zeros(n_u)
    u_hist, y_hist = [u] * lags, [y] * lags
    planner.reset()
    cost, tracked, us, ys = 0.0, list(tracked), [], []
    for k in range(steps):
        r = reference.evaluate(k * dt, dt, n)
        state = None if state_of is None else state_of(np.array(u_hist), np.array(y_hist))
        start = time.perf_counter()
        res = planner.solve(state, u, r, y, k)
        if times is not None:
            times.append(time.perf_counter() - start)
        u = np.asarray(res.u, float)
        u = np.clip(u if explore is None else u + explore[k], plant.u_min, plant.u_max)
        y = sim.step(u)
        if sim.diverged:
            return math.inf, (np.array(us).reshape(-1, n_u), np.array(ys).reshape(-1, len(r[0])))
        u_hist, y_hist = u_hist[1:] + [u], y_hist[1:] + [y]
        us.append(u)
        ys.append(y)
        cost += float(np.sum((y[tracked] - r[0, tracked]) ** 2))
    return cost, (np.array(us), np.array(ys))


def track(planner, plant: PlantConfig, theta: Sequence[float], x0: Sequence[float],
          reference, steps: int, tracked: Sequence[int],
          state_of: Optional[Callable] = None, lags: int = 1,
          times: Optional[List[float]] = None) -> float:
    """The tracking cost of one episode (module docstring; :func:`episode`'s arguments)."""
    return episode(planner, plant, theta, x0, reference, steps, tracked, state_of, lags,
                   times=times)[0]


@dataclass
class Target:
    """One test target of the study and everything the experiment's configuration says of
    its run: theta*, seed, the configuration at theta*, controller and plant settings."""

    theta: Tuple[float, ...]
    seed: int
    experiment: ExperimentConfig

    def controller(self):
        return self.experiment.node_config('controller', self.seed)

    def plant(self) -> PlantConfig:
        return plant_config(self.experiment.node_parameters('plant', self.seed), self.theta)


def closed_loop_record(model: FeatureNarx, tgt: 'Target', samples: int, exploration: float
                       ) -> Record:
    """`samples` target samples in closed loop near the operating region: the locally linear
    MPC on `model` tracks the target's reference from the tracking x0, a set-point sequence's
    segments shortened so that every set-point is held samples / (their number) samples, with
    the experiment's excitation (seed 30000 + the target's seed) at amplitude `exploration`,
    centred on zero, added to its input. Cut before an escape."""
    ctrl, plant = tgt.controller(), tgt.plant()
    params = dict(ctrl.reference_params)
    if 'segment' in params:
        params['segment'] = samples * plant.dt / len(params['setpoints'])
    explore = np.zeros((samples, len(plant.u_min)))
    if exploration > 0:
        band = replace(ctrl.excitation, amplitude=exploration, center=())
        lo, hi = band.band()
        explore = excitation(band, 1, samples, plant.dt, 30_000 + tgt.seed)[0] - (lo + hi) / 2
    return episode(LocalLinearMpc(ctrl.mpc, model), plant, tgt.theta, tgt.experiment.track_x0,
                   make_reference(ctrl.reference_kind, **params), samples,
                   tgt.experiment.tracked_outputs, model.state, model.shape.order, explore)[1]


def targets(config: RegimeConfig) -> List[Target]:
    """The study's targets in order (config.thetas x seeds, or each seed's own draw)."""
    if not config.thetas:
        base = experiment(config)
        return [Target(tuple(base.target_theta(s)), s, base) for s in config.seeds]
    out = []
    for theta in config.thetas:
        exp = experiment(config, theta)
        out += [Target(tuple(float(v) for v in theta), s, exp) for s in config.seeds]
    return out


def meta_models(config: RegimeConfig, log: Callable[[str], None],
                cache: Optional[str] = None) -> Dict[str, FeatureNarx]:
    """The feature NARX meta-trained by each method on the first seed's source systems;
    with `cache` (a folder) each meta-model is kept there under a hash of everything it
    depends on (source systems, sizes, meta-training settings) and read back when present."""
    exp = experiment(config)
    source = exp.node_config('learner', config.seeds[0]).source
    data = simulate_source(source)
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    fam = exp.plant_family
    order = config.order or exp.node_config('learner', config.seeds[0]).narx.order
    shape = NarxShape(fam.n_u, fam.n_y, order, config.features, tuple(config.hidden))
    systems = [[(t.u, t.y) for t in ts] for ts in data.trajectories if ts]
    out = {}
    for method in config.methods:
        meta_cfg = NarxMetaConfig(**{**config.meta.__dict__, 'method': method})
        key = hashlib.sha256(repr((source, shape, meta_cfg)).encode()).hexdigest()[:16]
        path = cache and os.path.join(cache, f'narx_{method}_{key}.pt')
        if path and os.path.exists(path):
            params = torch.load(path)
            log(f'meta-model {method}: {path}')
        else:
            res = meta_train(shape, norm, systems, meta_cfg)
            log(f'meta-trained {method}: D_test loss {np.mean(res.curve[:20]):.2e} -> '
                f'{np.mean(res.curve[-20:]):.2e} in {res.elapsed:.0f} s')
            params = res.params
            if path:
                torch.save(params, path)
        out[method] = FeatureNarx(shape, norm, params)
    return out


def _adapted(meta: FeatureNarx, gamma: float, toward_arx: bool, records: Sequence[Record]
             ) -> Tuple[FeatureNarx, float, str]:
    """(model, training loss, rule) of the adaptation (:func:`adapt`) to `records`."""
    ad = adapt(meta, records, gamma, toward_arx)
    return ad.model, ad.train_loss, ad.rule


def _least_squares(meta: FeatureNarx, records: Sequence[Record]
                   ) -> Tuple[FeatureNarx, float, str]:
    """(model, training loss, rule) of the least-squares ARX(p) of `records`."""
    model = arx_model(meta, records)
    return model, one_step_loss(model, records), 'least_squares'


def run(config: RegimeConfig, log: Callable[[str], None] = print,
        cache: Optional[str] = None) -> List[Dict]:
    """Every row of the study (module docstring): one dict per (target, model) with the
    tracking cost, its ratio to the NMPC's, held-out and training losses (``heldout``: the
    HELDOUT_HORIZON-step loss on open-loop samples; ``heldout_loop``: along the NMPC's own
    episode at the target, near the set-points, where the controller operates). With
    `cache` (a folder) each target's rows are kept there too, under a hash of the
    meta-models' weights, the target's configuration, theta*, seed and the study's settings,
    and read back when present: a study stopped part way resumes at its first target
    without rows."""
    metas = meta_models(config, log, cache)
    weights = hashlib.sha256()
    for method, meta in metas.items():
        weights.update(method.encode())
        for name, value in sorted(meta.params.items()):
            weights.update(name.encode() + value.detach().cpu().numpy().tobytes())
    settings = replace(config, thetas=(), seeds=())
    rows = []
    for tgt in targets(config):
        key = hashlib.sha256(repr((weights.hexdigest(), tgt.experiment, tgt.theta, tgt.seed,
                                   settings)).encode()).hexdigest()
        path = cache and os.path.join(cache, f'rows_{key[:16]}.json')
        if path and os.path.exists(path):
            with open(path) as f:
                own = json.load(f)
            log(f'theta* {list(tgt.theta)} seed {tgt.seed}: rows {path}')
        else:
            own = target_rows(tgt, metas, config, log)
            if path:
                with open(path + '.part', 'w') as f:
                    json.dump(own, f)
                os.replace(path + '.part', path)
        rows += own
    return rows


def target_rows(tgt: Target, metas: Dict[str, FeatureNarx], config: RegimeConfig,
                log: Callable[[str], None] = print) -> List[Dict]:
    """The rows of one target (:func:`run`): the NMPC's episode, then each model adapted to
    the target's samples (and the oracles) flown by the locally linear MPC."""
    rows = []
    exp, ctrl, plant = tgt.experiment, tgt.controller(), tgt.plant()
    steps, tracked = exp.track_steps(), list(exp.tracked_outputs)
    nmpc = fly(exp.node_parameters('controller', tgt.seed),
               exp.node_parameters('plant', tgt.seed), tgt.theta, exp.track_x0, steps)
    c_nmpc = (math.inf if nmpc.escaped_at is not None
              else nmpc.tracking_cost(tracked))
    log(f'theta* {list(tgt.theta)} seed {tgt.seed}: NMPC cost {c_nmpc:.4g}')
    # where the controller operates: the NMPC's own episode (u[k] produced y[k]), before
    # any escape
    end = len(nmpc.y) if nmpc.escaped_at is None else nmpc.escaped_at
    loop = [(nmpc.u[1:end], nmpc.y[1:end])]
    closed = round(config.closed_loop * exp.target_samples)
    recs = [collect(ctrl.excitation, plant, tgt.theta, exp.collect_x0,
                    exp.target_samples - closed, tgt.seed)]
    held = [collect(ctrl.excitation, plant, tgt.theta, exp.collect_x0, HELDOUT_SAMPLES,
                    10_000 + tgt.seed)]
    first = next(iter(metas.values()))
    fits = {method: partial(_adapted, meta, config.meta.gamma, config.toward_arx)
            for method, meta in metas.items()}
    fits['arx'] = partial(_least_squares, first)
    models = {}
    for name, fit in fits.items():
        models[name] = fit(recs)
        if closed:
            more = closed_loop_record(models[name][0], tgt, closed, config.exploration)
            models[name] = fit(recs + [more])
    if config.oracle:
        fam = exp.plant_family
        starts = np.random.default_rng([tgt.seed, 77]).uniform(
            fam.x0_low, fam.x0_high, (ORACLE_EPISODES, fam.n_x))
        # as the source set keeps them: whole episodes only, an escaping one dropped
        many = [r for r in (collect(ctrl.excitation, plant, tgt.theta, x0,
                                    ORACLE_SAMPLES, 20_000 + i)
                            for i, x0 in enumerate(starts))
                if len(r[1]) == ORACLE_SAMPLES]
        for method, meta in metas.items():
            oracle = adapt(meta, many, config.meta.gamma, config.toward_arx)
            models[f'oracle_{method}'] = (oracle.model, math.nan, f'oracle {oracle.rule}')
    reference = make_reference(ctrl.reference_kind, **ctrl.reference_params)
    for name, (model, train, rule) in models.items():
        planner = LocalLinearMpc(ctrl.mpc, model)
        cost = track(planner, plant, tgt.theta, exp.track_x0, reference, steps, tracked,
                     model.state, model.shape.order)
        row = dict(theta=list(tgt.theta), seed=tgt.seed, model=name, rule=rule,
                   cost=cost, nmpc=c_nmpc, ratio=cost / c_nmpc, train_loss=train,
                   heldout=heldout_loss(model, held, HELDOUT_HORIZON),
                   heldout_loop=heldout_loss(model, loop, HELDOUT_HORIZON),
                   failed_linearisations=planner.failed_linearisations)
        rows.append(row)
        log(f'  {name:>13}: cost {cost:9.4g} ratio {cost / c_nmpc:7.3f} held-out '
            f'{row["heldout"]:.2e}, along the NMPC {row["heldout_loop"]:.2e} ({rule})')
    return rows


def summary(rows: Sequence[Dict]) -> List[str]:
    """Markdown lines: per model the cost / NMPC median and worst, escapes and the median
    held-out l_SSM (open loop, and along the NMPC's episode); then each method against the
    ARX of the same samples, paired by target
    (:func:`~metampc_bringup.analysis.paired_stats.paired_claim` on the cost ratio)."""
    models = list(dict.fromkeys(r['model'] for r in rows))
    lines = ['| model | cost / NMPC median | worst | escapes | held-out l_SSM median | along '
             'the NMPC |', '|---|---|---|---|---|---|']
    for name in models:
        own = [r for r in rows if r['model'] == name]
        ratios = [r['ratio'] for r in own]
        lines.append(f'| {name} | {np.median(ratios):.3f} | {max(ratios):.3f} | '
                     f'{sum(not math.isfinite(r["cost"]) for r in own)}/{len(own)} | '
                     f'{np.median([r["heldout"] for r in own]):.2e} | '
                     f'{np.median([r["heldout_loop"] for r in own]):.2e} |')
    arx = [r['cost'] for r in rows if r['model'] == 'arx']
    for name in models:
        if name == 'arx' or name.startswith('oracle'):
            continue
        own = [r['cost'] for r in rows if r['model'] == name]
        lines.append(f'\n{name} < arx (paired): '
                     f'{format_claim(paired_claim(own, arx, log=True))}')
    return lines


__all__ = ['RegimeConfig', 'Target', 'collect', 'episode', 'track', 'closed_loop_record',
           'targets', 'meta_models', 'run', 'target_rows', 'summary']
