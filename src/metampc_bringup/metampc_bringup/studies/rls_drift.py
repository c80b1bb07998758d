"""The drift scenario flown by the feature NARX, with and without the in-loop RLS of its head.

One process, no ROS (``scripts/rls_drift.py``). The feature NARX is meta-trained once on the
first seed's source systems (:func:`~metampc_bringup.studies.nonlinear_regime.meta_models`),
then per seed adapted to the target's samples as the experiment collects them, sent through the
weights message's fields, and flown by the controller core (:func:`~metampc_bringup.analysis.
retrack.fly`) under each variant's controller parameters, while theta* changes as the
experiment's ``drift.schedule`` says (or, with ``centre_step``, each component moves by that
toward the middle of its prior's support at mid-run); the true-model NMPC, told theta at every
step, is the yardstick. Costs before and after the change; the same at constant theta*. A
variant whose ``adaptation`` is not off has its requests answered in the loop by the
learner's closed-form adaptation on the latest ``loop_window`` samples (:func:`answer_requests`).
"""
from dataclasses import dataclass, field
import math
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence

import numpy as np

from metampc_bringup.analysis.retrack import fly, plant_config
from metampc_bringup.studies.nonlinear_regime import (collect, experiment, meta_models,
                                                      RegimeConfig)
from metampc_controller.adaptation_trigger import Request
from metampc_controller.closed_loop import Learner
from metampc_controller.controller_core import build_model, ControllerCore
from metampc_learner.narx_learning import adapt
from metampc_model.feature_narx import FeatureNarx
from metampc_model.weights_codec import fields_from_narx, model_from_fields


@dataclass
class RlsDriftConfig:
    """Attributes:
        regime: the experiment file, the feature NARX's sizes and meta-training (its first seed
            names the source systems; its gamma is the adaptation's).
        seeds: test or validation seeds (theta* the experiment's draw for each).
        variants: name -> controller parameters over the experiment's ('none': {}).
        centre_step: None: the experiment's drift.schedule; else theta moves by this toward
            the middle of each component's prior support at half the run.
        constant: also fly every variant at constant theta*.
        nmpc: fly the NMPC yardstick (False: the ratios to it are NaN; the quadruple tank's
            IPOPT takes minutes per drift episode on some seeds).
    """

    regime: RegimeConfig = field(default_factory=RegimeConfig)
    seeds: Sequence[int] = (0,)
    variants: Mapping[str, Mapping[str, Any]] = field(default_factory=lambda: {'none': {}})
    centre_step: Optional[float] = None
    constant: bool = True
    nmpc: bool = True


def schedule(config: RlsDriftConfig, theta: Sequence[float], steps: int, dt: float
             ) -> List[float]:
    """The plant's theta_schedule of a drift run at theta* (flat rows [t0, t1, theta...])."""
    exp = experiment(config.regime)
    if config.centre_step is None:
        return exp.drift_config().theta_schedule(list(theta))
    t = steps * dt / 2
    moved = []
    for value, comp in zip(theta, exp.plant_family.theta):
        lo, hi = comp.support
        moved.append(value + config.centre_step * float(np.sign((lo + hi) / 2 - value)))
    return [t, t, *moved]


def decoded(model: FeatureNarx):
    """A feature NARX as the controller receives it (through the weights message's fields)."""
    return model_from_fields(fields_from_narx(model.shape, model.norm, model.params))


def answer_requests(meta: FeatureNarx, gamma: float, window: int, rules: List[str]
                    ) -> Learner:
    """The learner in one process: each request of step k is answered by ``adapt(meta,
    [the latest `window` samples up to k], gamma)`` (stage 'online', the next version), offered
    to the core's gate naming the request; its rule is appended to `rules` ('refused: ...' where
    adapt raises)."""
    def learner(core: ControllerCore, request: Request, u: np.ndarray, y: np.ndarray) -> None:
        first = max(0, len(y) - window)
        try:
            model = adapt(meta, [(u[first:], y[first:])], gamma)
        except ValueError as err:
            rules.append(f'refused: {err}')
            core.gate.learner_refused(request.step)
            return
        rules.append(model.rule)
        version = max(request.version, core.model.version if core.model else 0) + 1
        core.offer(build_model(decoded(model.model), version, 'imaml', 'online',
                               core.config.mpc, core.n_u, core.n_y, core.config.history),
                   request.step)
    return learner


def _costs(episode, tracked: Sequence[int], change: int) -> Dict[str, float]:
    """Sums of squared tracking errors up to sample `change` and after it (inf: escaped)."""
    if episode.escaped_at is not None:
        return {'before': math.inf, 'after': math.inf}
    err = (episode.y[1:, list(tracked)] - episode.y_ref[:, list(tracked)]) ** 2
    return {'before': float(err[:change].sum()), 'after': float(err[change:].sum())}


def run_seed(config: RlsDriftConfig, seed: int, meta, log: Callable[[str], None] = print
             ) -> List[Dict[str, Any]]:
    """Every row of one seed: per run ('drift', and 'constant' with ``constant``) the NMPC's
    costs and each variant's, with its ratios to the NMPC's and the RLS's counts."""
    exp = experiment(config.regime)
    theta = exp.target_theta(seed)
    ctrl = exp.node_config('controller', seed)
    plant = plant_config(exp.node_parameters('plant', seed), theta)
    record = collect(ctrl.excitation, plant, theta, exp.collect_x0, exp.target_samples, seed)
    gamma = config.regime.meta.gamma
    adapted = adapt(meta, [record], gamma)
    weights = decoded(adapted.model)
    learner_params = exp.node_parameters('learner', seed)
    window = (learner_params.get('loop_window')
              or learner_params.get('target_buffer_size', exp.target_samples))
    duration = exp.drift_config().duration if config.centre_step is None else (
        exp.track_duration)
    steps = int(round(duration / exp.dt))
    drift = schedule(config, theta, steps, exp.dt)
    change = int(round(drift[0] / exp.dt))
    controller = exp.node_parameters('controller', seed)
    tracked = list(exp.tracked_outputs)
    runs = {'drift': drift, **({'constant': []} if config.constant else {})}
    rows = []
    for run, sched in runs.items():
        plant_params = {**exp.node_parameters('plant', seed), 'theta_schedule': sched}
        nmpc = (_costs(fly(controller, plant_params, theta, exp.track_x0, steps), tracked,
                       change) if config.nmpc else {'before': math.nan, 'after': math.nan})
        for name, overrides in config.variants.items():
            values = {**controller, **overrides}
            rules: List[str] = []
            learner = (answer_requests(meta, gamma, window, rules)
                       if values.get('adaptation', 'off') != 'off' else None)
            episode = fly(values, plant_params, theta, exp.track_x0, steps, weights, learner)
            cost = _costs(episode, tracked, change)
            counts = episode.ticks[-1].rls_counts if episode.ticks else None
            requests = [t.step for t in episode.ticks if t.request is not None]
            rows.append(dict(seed=seed, theta=list(theta), run=run, variant=name,
                             rule=adapted.rule, escaped=episode.escaped_at is not None,
                             nmpc_before=nmpc['before'], nmpc_after=nmpc['after'], **cost,
                             ratio_before=cost['before'] / nmpc['before'],
                             ratio_after=cost['after'] / nmpc['after'],
                             counts=dict(counts.__dict__) if counts is not None else None,
                             requests=requests, answers=rules))
            log(f'seed {seed} {run:>8} {name:>16}: after / NMPC {rows[-1]["ratio_after"]:.4f}'
                f' before {rows[-1]["ratio_before"]:.4f} {rows[-1]["counts"] or ""}'
                + (f' requests at {requests}: {rules}' if requests else ''))
    return rows


def run(config: RlsDriftConfig, log: Callable[[str], None] = print,
        cache: Optional[str] = None) -> List[Dict[str, Any]]:
    """Every row of every seed (:func:`run_seed`), the meta-model made or read once."""
    meta = meta_models(config.regime, log, cache)[config.regime.methods[0]]
    return [row for seed in config.seeds for row in run_seed(config, seed, meta, log)]


def paired(rows: Sequence[Dict[str, Any]], variant: str, baseline: str = 'none',
           run: str = 'drift', key: str = 'after') -> Dict[int, float]:
    """{seed: cost of `variant` / cost of `baseline`} over `run`'s `key` cost."""
    own = {r['seed']: r[key] for r in rows if r['variant'] == variant and r['run'] == run}
    base = {r['seed']: r[key] for r in rows if r['variant'] == baseline and r['run'] == run}
    return {s: own[s] / base[s] for s in sorted(own) if s in base}


__all__ = ['RlsDriftConfig', 'schedule', 'decoded', 'answer_requests', 'run_seed', 'run',
           'paired']
