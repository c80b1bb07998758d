"""The experiment's learning set-up without ROS: meta-training and adaptation jobs.

What ``scripts/tune.py``, ``scripts/robustness.py`` and ``scripts/sweep_inner_steps.py`` share:
the learner configuration an experiment gives a seed (:func:`settings_from`), validation
targets that are never the experiment's test targets (theta_i from ``rng([1000 + i, 0x5a1])``,
with ``target_samples`` adaptation samples and :data:`HELDOUT_SAMPLES` held out; the test
targets come from ``rng([s, 0x7e7a])``), a job on one test target (``target_theta``, data seeded
by :func:`target_data_seeds`), and a job (:func:`run_job`) in a process set up by :func:`use`;
the jobs run on the cluster layer with their results cached on disk
(:mod:`metampc_bringup.studies.study_jobs`). Protocols: docs/tuning.md, docs/sweep.md. No rclpy
here.
"""
import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from metampc_bringup.analysis.retrack import fly
from metampc_bringup.experiment_config import ExperimentConfig, learner_config, load
from metampc_bringup.studies.pruning import pruned_at, REPORT_EVERY, reports
from metampc_learner.adapt import GAUSS_NEWTON
from metampc_learner.data import (normalisation_from, simulate_source, simulate_target,
                                  SourceSet, Trajectory)
from metampc_learner.learner_params import AdaptJob, fit_settings, LearnerNodeConfig
from metampc_learner.meta_train import meta_train, MetaConfig, MetaTrainingError
from metampc_learner.progress import Progress
from metampc_learner.target_fit import fit_target, TargetFit
from metampc_model.nssm import Nssm
from metampc_model.weights_codec import DecodedWeights, WeightsError
from metampc_plant.family import PlantFamily

VALIDATION_SEED = 1000       # validation source set, meta seed and supervised init seed
THETA_STREAM = 0x5a1         # validation thetas: rng([VALIDATION_SEED + i, THETA_STREAM])
HELDOUT_SAMPLES = 600
TEST_HELDOUT_SAMPLES = 2000
TEST_DATA_STREAM = 0x7e57    # test target data: SeedSequence([source_seed, TEST_DATA_STREAM])
CURVE_STEPS = (0, 1, 5, 20)  # held-out loss reported after these adaptation steps


def request_meta_config(experiment: ExperimentConfig, method: str) -> Dict[str, Any]:
    """The experiment's MetaTrain request fields of `method` as MetaConfig fields (online
    collection, a request flag, is not one)."""
    fields = dict(experiment.meta_train.get(method) or {})
    fields.pop('online_collection', None)
    return fields


@dataclass
class Settings:
    """What every job needs to rebuild the set-up (picklable).

    Attributes:
        learner: the experiment's learner configuration (its source seed is replaced per job).
        thetas: the validation targets.
        target_samples: adaptation samples per target.
        adapt_steps: adaptation steps scored.
        meta_defaults: MetaConfig fields applied before a job's own (e.g. cg_steps).
        control: closed-loop scoring (None: prediction only); see :class:`ControlScoring`.
    """

    learner: LearnerNodeConfig
    thetas: Tuple[Tuple[float, ...], ...]
    target_samples: int
    adapt_steps: int
    meta_defaults: Dict[str, Any] = field(default_factory=dict)
    control: Optional['ControlScoring'] = None


@dataclass
class ControlScoring:
    """Closed-loop scoring of adapted models (the tuning's control score).

    Each adapted model of a validation target tracks the experiment's reference in one
    process (the experiment's controller core and plant core, :mod:`closed_loop`), from the
    experiment's track_x0 for its track_duration; its cost over the true-model NMPC's on the
    same target is the target's ratio (inf when the plant escapes or the model is rejected).
    A step size's control score is the geometric mean of the ratios over the targets.

    Attributes:
        controller: the controller node's parameter values (the experiment's section).
        plant: the plant node's parameter values (the experiment's; theta is each target's).
        x0, steps, tracked: track_x0, samples of a tracking run, tracked outputs.
        nmpc: the NMPC's tracking cost of each validation target (computed once).
    """

    controller: Dict[str, Any]
    plant: Dict[str, Any]
    x0: Tuple[float, ...]
    steps: int
    tracked: Tuple[int, ...]
    nmpc: Tuple[float, ...] = ()


@dataclass
class Validation:
    """The set-up of one source set: NSSM with its normalisation, source set, and per target
    its adaptation and held-out trajectories (physical)."""

    model: Nssm
    source: SourceSet
    train: List[List[Trajectory]]
    heldout: List[List[Trajectory]]


@dataclass
class Job:
    """One run: meta-train (unless supervised), then adapt with each step size.

    Attributes:
        method: 'imaml', 'maml', 'maml_unrolled' or 'supervised'.
        index: configuration number within its search or sweep.
        hyper: MetaConfig fields of this run (empty for supervised).
        iterations: outer steps.
        lrs: adaptation step sizes to score (empty: meta-training only).
        stage: free label ('search', 'refine', 'robust', 'sweep', ...).
        source_seed: seed of the source set and of meta-training.
        nssm: NssmConfig fields that differ from the experiment's (e.g. rho_max).
        target_theta: None: scored on the validation targets of the settings; else on this
            one target (the test target of the run whose seed is `source_seed`).
        heldout_samples: held-out samples per target.
        prune_above: the median pruner's thresholds at each report step of meta-training
            (:mod:`.pruning`); None: never pruned.
    """

    method: str
    index: int
    hyper: Dict[str, Any]
    iterations: int
    lrs: Tuple[float, ...]
    stage: str
    source_seed: int = VALIDATION_SEED
    nssm: Dict[str, Any] = field(default_factory=dict)
    target_theta: Optional[Tuple[float, ...]] = None
    heldout_samples: int = HELDOUT_SAMPLES
    prune_above: Optional[Tuple[float, ...]] = None

    def cost(self) -> float:
        """Rough relative cost, to start the long jobs first."""
        if self.method == 'supervised':
            return 0.0
        per_step = 1.5 if self.method == 'imaml' else 1.0
        return self.iterations * per_step * (4 + self.hyper.get('inner_steps', 10))

    def __str__(self) -> str:
        """A short name (progress, errors, the job's key on the cluster)."""
        return f'{self.method}-{self.stage}-{self.index}-seed{self.source_seed}'

    def key(self, settings: Settings) -> str:
        """A name for the cached result: a hash of the job and of the settings."""
        fields = {k: v for k, v in asdict(self).items()
                  if k not in _LATER_FIELDS or v != _LATER_FIELDS[k]}
        blob = json.dumps([fields, repr(settings)], sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:20]


# Fields added after results were cached: hashed only when set, so those keep their names.
_LATER_FIELDS = {'target_theta': None, 'heldout_samples': HELDOUT_SAMPLES,
                 'prune_above': None}


def target_data_seeds(source_seed: int) -> Tuple[int, int]:
    """Seeds of a test target's (adaptation, held-out) data: the first two 64-bit words of
    ``SeedSequence([source_seed, TEST_DATA_STREAM])``, shared with no other stream."""
    words = np.random.SeedSequence([source_seed, TEST_DATA_STREAM]).generate_state(2, np.uint64)
    return int(words[0]), int(words[1])


def validation_thetas(n: int, family: PlantFamily) -> Tuple[Tuple[float, ...], ...]:
    """theta_i drawn from the family's prior with rng([VALIDATION_SEED + i, THETA_STREAM]),
    i = 0..n-1 (van der Pol: the normal draw N(0, 1) of that generator)."""
    return tuple(tuple(family.sample_theta(
        np.random.default_rng([VALIDATION_SEED + i, THETA_STREAM]), 1)[0].tolist())
        for i in range(n))


def settings_from(config_path: str, n_thetas: int, adapt_steps: int,
                  meta_defaults: Optional[Dict[str, Any]] = None,
                  control: bool = False) -> Settings:
    """Settings from an experiment YAML: its learner set-up, validation targets, and with
    `control` the closed-loop scoring (the NMPC's costs on the targets are computed here:
    seconds to a minute per target)."""
    experiment = load(config_path)
    thetas = validation_thetas(n_thetas, experiment.plant_family)
    scoring = None
    if control:
        cfg = experiment.resolved()
        scoring = ControlScoring(cfg.node_parameters('controller', VALIDATION_SEED),
                                 cfg.node_parameters('plant', VALIDATION_SEED),
                                 tuple(cfg.track_x0), cfg.track_steps(),
                                 tuple(cfg.tracked_outputs))
        scoring = replace(scoring, nmpc=tuple(track(scoring, theta, None)
                                              for theta in thetas))
    return Settings(learner_config(experiment, VALIDATION_SEED), thetas,
                    experiment.target_samples, adapt_steps, dict(meta_defaults or {}),
                    scoring)


def track(scoring: 'ControlScoring', theta: Sequence[float], model) -> float:
    """Tracking cost of the adapted NSSM `model` ((config, norm, params), or None for the
    true-model NMPC) on the target theta (:func:`retrack.fly`); inf when the plant escapes
    or the controller rejects the model."""
    try:
        episode = fly(scoring.controller, scoring.plant, theta, scoring.x0, scoring.steps,
                      None if model is None else DecodedWeights(*model))
    except WeightsError:
        return math.inf
    if episode.escaped_at is not None:
        return math.inf
    return episode.tracking_cost(scoring.tracked)


def build_validation(settings: Settings, source_seed: int, nssm: Dict[str, Any],
                     target_theta: Optional[Sequence[float]] = None,
                     heldout_samples: int = HELDOUT_SAMPLES) -> Validation:
    """Simulate a source set and the targets' adaptation and held-out trajectories: the validation
    targets (the same data for every source set), or the one test target `target_theta`
    (data seeded by :func:`target_data_seeds` of `source_seed`); the normalisation is the
    source set's."""
    cfg = settings.learner
    nssm_config = replace(cfg.nssm, **nssm)
    data = simulate_source(replace(cfg.source, seed=source_seed))
    model = Nssm(nssm_config, normalisation_from([t for ts in data.trajectories for t in ts]))
    source = SourceSet(data, model.norm, nssm_config, cfg.train_fraction)
    one_episode = replace(cfg.source, episode_samples=settings.target_samples)
    targets = ([(target_theta, *target_data_seeds(source_seed))] if target_theta is not None
               else [(theta, 10 * (VALIDATION_SEED + i) + 1, 10 * (VALIDATION_SEED + i) + 2)
                     for i, theta in enumerate(settings.thetas)])
    # simulate_target's default of 20 episodes for up to 5 needed: the validation data as
    # before; a larger held-out set gets 4 per needed one (measured: at most 14 % of the
    # episodes escape for theta in [-3.5, 3.5]).
    attempts = max(20, 4 * math.ceil(heldout_samples / cfg.source.episode_samples))
    train, heldout = [], []
    for theta, train_seed, heldout_seed in targets:
        train.append(simulate_target(theta, one_episode, settings.target_samples, train_seed))
        heldout.append(simulate_target(theta, cfg.source, heldout_samples, heldout_seed,
                                       attempts))
    return Validation(model, source, train, heldout)


_SETTINGS: Optional[Settings] = None
_VALIDATIONS: Dict[str, Validation] = {}


def use(settings: Settings, threads: int) -> None:
    """In a process that runs jobs, before each: its torch threads and the job's settings;
    the set-ups built for other settings are dropped (a worker of a long-lived cluster serves
    one study after another)."""
    global _SETTINGS
    torch.set_num_threads(threads)
    if settings != _SETTINGS:
        _SETTINGS = settings
        _VALIDATIONS.clear()


def validation(source_seed: int, nssm: Dict[str, Any],
               target_theta: Optional[Sequence[float]] = None,
               heldout_samples: int = HELDOUT_SAMPLES) -> Validation:
    """The set-up of a source seed, NSSM and targets (see :func:`build_validation`), built
    once per process and settings (:func:`use`)."""
    key = json.dumps([source_seed, nssm, target_theta, heldout_samples], sort_keys=True)
    if key not in _VALIDATIONS:
        _VALIDATIONS[key] = build_validation(_SETTINGS, source_seed, nssm, target_theta,
                                             heldout_samples)
    return _VALIDATIONS[key]


def meta_config(job: Job, settings: Settings) -> MetaConfig:
    """The MetaConfig of a meta job: its fields on the experiment's learner defaults."""
    return replace(settings.learner.meta, method=job.method, iterations=job.iterations,
                   seed=job.source_seed, **{**settings.meta_defaults, **job.hyper})


def returned_loss(result) -> float:
    """The validation loss of the weights meta-training returned (its best checkpoint under
    the divergence guard); without validations, the mean of the last 10 training losses."""
    losses = dict(result.validation_losses)
    if result.best_iteration in losses:
        return float(losses[result.best_iteration])
    return float(np.mean(result.losses[-10:]))


def _spectrum(params) -> Dict[str, float]:
    a = params['A'].detach().double()
    return {'a_radius': float(torch.linalg.eigvals(a).abs().max()),
            'a_norm': float(torch.linalg.matrix_norm(a, ord=2))}


class Pruned(Exception):
    """Meta-training stopped by the median pruner at outer step `step`."""

    def __init__(self, step: int):
        super().__init__(f'pruned at step {step}')
        self.step = step


def _pruning(thresholds: Optional[Sequence[float]], losses: List[float]):
    """A meta-training progress callback that keeps the losses in `losses` and raises
    :class:`Pruned` where the median pruner's `thresholds` stop the trial; None without."""
    if thresholds is None:
        return None

    def check(progress: Progress) -> None:
        losses.append(progress.loss)
        if progress.iteration % REPORT_EVERY == 0 and \
                pruned_at(reports(losses), thresholds) == progress.iteration:
            raise Pruned(progress.iteration)
    return check


def run_job(job: Job) -> dict:
    """Meta-train (meta methods), then score every step size (one under the experiment's
    ``adapt_rule: gauss_newton``, which takes none); a failure scores inf.

    The result holds the meta-training curve (every 10th step; the pruner's reports, means
    of every 10 steps: :mod:`.pruning`), its final loss (mean of the last 10 steps), the
    largest loss, the spectral radius and norm of the meta-model's A,
    and per step size the held-out loss of every validation target after ``CURVE_STEPS``
    steps; ``score`` is the mean held-out loss after the last step at the best step size
    (the final meta loss when no step size is scored). A job stopped by its median pruner
    (``prune_above``) holds where (``pruned_at``), its reports and an inf score.
    """
    settings = _SETTINGS
    val = validation(job.source_seed, job.nssm, job.target_theta, job.heldout_samples)
    cpu = time.process_time()
    out: Dict[str, Any] = {'method': job.method, 'index': job.index, 'stage': job.stage,
                           'hyper': job.hyper, 'nssm': job.nssm,
                           'iterations': job.iterations if job.method != 'supervised' else 0,
                           'source_seed': job.source_seed}
    if job.target_theta is not None:
        out.update(target_theta=job.target_theta, heldout_samples=job.heldout_samples)
    params = None
    if job.method != 'supervised':
        losses_so_far: List[float] = []
        try:
            result = meta_train(val.model, val.source, meta_config(job, settings),
                                _pruning(job.prune_above, losses_so_far))
        except MetaTrainingError as err:
            return {**out, 'error': str(err), 'score': math.inf, 'adapt': [],
                    'cpu_seconds': round(time.process_time() - cpu, 1)}
        except Pruned as stop:
            return {**out, 'pruned_at': stop.step, 'meta_loss_reports': reports(losses_so_far),
                    'score': math.inf, 'adapt': [],
                    'cpu_seconds': round(time.process_time() - cpu, 1)}
        params = result.params
        losses = np.array(result.losses)
        out.update(meta_final_loss=float(np.mean(losses[-10:])),
                   meta_loss_reports=reports(result.losses),
                   meta_max_loss=float(np.max(losses)) if np.all(np.isfinite(losses))
                   else math.inf,
                   meta_loss_every_10=[float(v) for v in losses[9::10]],
                   meta_skipped=result.skipped, meta_seconds=round(result.elapsed, 1),
                   meta_returned_loss=returned_loss(result),
                   meta_rollbacks=list(result.rollbacks),
                   meta_best_iteration=result.best_iteration,
                   meta_cg_residual=float(np.nanmean(result.cg_residuals[-10:]))
                   if job.method == 'imaml' else None,
                   **_spectrum(params))
    out['adapt'] = []
    start = time.monotonic()
    scoring = settings.control if job.target_theta is None else None
    learner = settings.learner    # the experiment's step rule and gain check, as it adapts
    # gauss_newton takes no step size: one is scored, the others would repeat it.
    for lr in job.lrs[:1] if learner.adapt.rule == GAUSS_NEWTON else job.lrs:
        fit = replace(fit_settings(learner, AdaptJob(job.method, settings.adapt_steps, lr,
                                                     0.0, 0)), seed=VALIDATION_SEED)
        curves: List[List[float]] = []
        ratios: List[float] = []
        for i, (train, held) in enumerate(zip(val.train, val.heldout)):
            try:
                fitted: Optional[TargetFit] = fit_target(job.method, val.model, params, train,
                                                         held, fit)
                curves.append(fitted.result.heldout_loss)
            except ValueError:
                curves.append([math.inf] * (settings.adapt_steps + 1))
                fitted = None
            if scoring is not None:
                flown = None if fitted is None else fitted.model   # the ARX where refused
                cost = math.inf if fitted is None else track(
                    scoring, settings.thetas[i], (flown.config, flown.norm,
                                                  fitted.result.params))
                ratios.append(cost / scoring.nmpc[i])
        final = [c[-1] for c in curves]
        entry = {'lr': lr, 'score': float(np.mean(final)), 'heldout_final': final,
                 'heldout_at': {str(k): [c[k] for c in curves]
                                for k in CURVE_STEPS if k <= settings.adapt_steps}}
        if scoring is not None:
            # Control decides: a configuration that predicts better and controls worse loses.
            entry.update(prediction_score=entry['score'], control_ratios=ratios,
                         score=float(np.exp(np.mean(np.log(ratios)))))
        out['adapt'].append(entry)
    out['adapt_seconds'] = round(time.monotonic() - start, 1)
    out['cpu_seconds'] = round(time.process_time() - cpu, 1)
    if out['adapt']:
        best = min(out['adapt'], key=lambda a: a['score'])
        out.update(score=best['score'], best_lr=best['lr'])
    else:
        out['score'] = out.get('meta_final_loss', math.inf)
    return out


__all__ = ['VALIDATION_SEED', 'THETA_STREAM', 'HELDOUT_SAMPLES', 'TEST_HELDOUT_SAMPLES',
           'TEST_DATA_STREAM', 'CURVE_STEPS', 'Settings', 'Validation', 'Job',
           'request_meta_config', 'target_data_seeds', 'validation_thetas', 'settings_from',
           'build_validation', 'use', 'validation', 'meta_config', 'run_job']
