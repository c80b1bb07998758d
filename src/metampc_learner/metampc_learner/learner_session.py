"""What the learner node does, without ROS: meta-train, adapt, keep and save the models.

A :class:`LearnerSession` holds the meta-model omega_inf of every method it has trained or
loaded, numbers each model it makes (continuing after the highest in ``checkpoint_dir``, where
each is saved) and serves the node's jobs one at a time: :meth:`LearnerSession.meta_train`
(Algorithm 1, optionally with online collection, eq. (ub)), :meth:`LearnerSession.adapt`
(eq. (infer), or the 'supervised' / 'oracle' / 'arx' baselines, with the gain check: all by
:func:`~metampc_learner.target_fit.fit_target`) and :meth:`LearnerSession.loop_adapt`. With
``model_class`` 'feature_narx' the models are feature NARXs (:mod:`.narx_learning`; no gain
check, no adaptation in the loop); a request may name the other class (its meta-models kept
apart). Requests it cannot carry out raise :class:`LearnerError`.
Services and versions: docs/learner.md.
"""
import math
import os
import re
import time
from dataclasses import dataclass, field, replace
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np

from metampc_model.feature_narx import FeatureNarx, init_params as narx_init_params
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import Nssm, Params
from metampc_model.weights_codec import fields_from_narx, fields_from_weights
from metampc_learner import narx_learning
from metampc_learner.adapt import adapt, AdaptResult
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
from metampc_learner.data import (longest_run, normalisation_from, samples_in,
                                  simulate_source, SourceConfig, SourceData, SourceSet,
                                  Trajectory, Windows)
from metampc_learner.heldout import plant_source
from metampc_learner.learner_params import AdaptJob, fit_settings, LearnerNodeConfig
from metampc_learner.meta_train import META_METHODS, meta_train, MetaConfig
from metampc_learner.narx_learning import NarxMetaConfig
from metampc_learner.online_collection import CollectionStats, OnlineCollector
from metampc_learner.oracle import oracle_data
from metampc_learner.progress import Progress, ProgressFn
from metampc_learner.target_buffer import split_target, TargetSamples
from metampc_learner.target_fit import (ARX, BASELINES, FitError, fit_target,
                                        NARX_ADAPT_METHODS, ORACLE)
from metampc_plant.plant_description import PlantDescription

FINAL_LOSS_STEPS = 10   # final_loss of meta_train: mean meta-test loss of the last 10 steps
CHECKPOINT_NAME = re.compile(r'(?:meta|adapted|online)_[a-z_]+_v(\d+)\.pt')
KEPT_RECORDS = 64       # models kept by version for adaptation in the loop (the latest)


class LearnerError(RuntimeError):
    """A request that cannot be carried out; the message says what is missing or wrong."""


@dataclass
class ModelRecord:
    """A trained model with what the NssmWeights message carries besides the weights.

    Attributes:
        model: architecture and normalisation (an Nssm, or a FeatureNarx, which holds its
            params too).
        params: the weights (omega_inf for stage 'meta', omega* for 'adapted').
        method: 'imaml', 'maml', 'maml_unrolled', 'supervised', 'oracle' or 'arx'.
        stage: 'meta' or 'adapted'.
        version: number of this model (increases with every model of the session).
        train_loss: final training loss, normalised units.
        train_steps: outer steps (meta) or adaptation steps (adapted).
        train_samples: samples trained on.
        seed: seed of the run.
        train_time: wall time the training took, s (0 for a loaded model).
    """

    model: Union[Nssm, FeatureNarx]
    params: Params
    method: str
    stage: str
    version: int
    train_loss: float
    train_steps: int
    train_samples: int
    seed: int
    train_time: float = 0.0

    def fields(self) -> Dict[str, Any]:
        """The model fields of its NssmWeights message (:mod:`metampc_model.weights_codec`)."""
        model = self.model
        if isinstance(model, FeatureNarx):
            return fields_from_narx(model.shape, model.norm, self.params)
        return fields_from_weights(model.config, model.norm, self.params)

    @property
    def model_class(self) -> str:
        """'feature_narx' or 'nssm' (weights_codec.MODEL_CLASSES)."""
        return 'feature_narx' if isinstance(self.model, FeatureNarx) else 'nssm'


@dataclass
class MetaOutcome:
    """A finished meta-training: the record, the loss curve (mean meta-test loss per outer
    step), final_loss, skipped tasks, collection counters (None without collection)."""

    record: ModelRecord
    losses: List[float]
    final_loss: float
    skipped: int
    collection: Optional[CollectionStats]
    collected_samples: int
    dropped_samples: int
    elapsed: float


@dataclass
class AdaptOutcome:
    """A finished adaptation: the record, the core's result (held-out curve: index 0 before
    the first step), and the samples of D_target used (in all, for training, held out); with
    ``gain_check`` on, its verdict (`gain_check`: one line, '' when not checked) and the
    method whose model flies in the adapted one's place (`replaced_by`: 'arx' or ''); a feature
    NARX's closed-form fit (`rule`: :class:`~metampc_learner.narx_learning.AdaptedNarx`'s,
    'least_squares' for the arx; '' for an NSSM)."""

    record: ModelRecord
    result: AdaptResult
    used_samples: int
    train_samples: int
    heldout_samples: int
    gain_check: str = ''
    replaced_by: str = ''
    rule: str = ''


@dataclass
class LearnerSession:
    """The learner's state: meta-models per model class and method (`by_class`, `latest`),
    versions, cached source data."""

    config: LearnerNodeConfig
    by_class: Dict[str, Dict[str, ModelRecord]] = field(default_factory=dict)
    records: Dict[int, ModelRecord] = field(default_factory=dict)   # by version, the latest
    latest: Dict[str, str] = field(default_factory=dict)    # per class, its latest method
    version: int = 0
    _source: Optional[SourceData] = field(default=None, repr=False)

    def __post_init__(self):
        directory = self.config.checkpoint_dir
        if directory and os.path.isdir(directory):
            found = (CHECKPOINT_NAME.fullmatch(name) for name in os.listdir(directory))
            self.version = max([int(m.group(1)) for m in found if m] + [self.version])

    # --- models ---------------------------------------------------------------------------

    def _new_record(self, **kw) -> ModelRecord:
        self.version += 1
        record = ModelRecord(version=self.version, **kw)
        self.records[record.version] = record
        for old in sorted(self.records)[:-KEPT_RECORDS]:
            del self.records[old]
        if record.stage == 'meta':
            self.by_class.setdefault(record.model_class, {})[record.method] = record
            self.latest[record.model_class] = record.method
        self._save(record)
        return record

    def _save(self, record: ModelRecord) -> None:
        directory = self.config.checkpoint_dir
        if not directory:
            return
        os.makedirs(directory, exist_ok=True)
        path = os.path.join(directory, f'{record.stage}_{record.method}_v{record.version}.pt')
        save_checkpoint(path, record.model, record.params, {
            'method': record.method, 'stage': record.stage, 'version': record.version,
            'train_loss': record.train_loss, 'train_steps': record.train_steps,
            'train_samples': record.train_samples, 'seed': record.seed,
            'dt': self._dt()})

    def load_meta(self, path: str) -> ModelRecord:
        """Load a checkpoint as the meta-model of its method (info 'method', default imaml).

        Raises:
            LearnerError: unreadable file, a method that is not a meta method, or a model
                trained at another dt than this learner's (info 'dt', when it has one).
        """
        try:
            ckpt = load_checkpoint(path)
        except (OSError, ValueError, RuntimeError, KeyError, TypeError) as err:
            raise LearnerError(f'cannot load meta-model {path!r}: {err}') from None
        info = ckpt.info
        method = info.get('method', 'imaml')
        if method not in META_METHODS:
            raise LearnerError(f'{path!r} holds a {method!r} model, not a meta-model of '
                               f'{", ".join(META_METHODS)}')
        dt = self._dt()
        if 'dt' in info and not math.isclose(info['dt'], dt, rel_tol=1e-9):
            raise LearnerError(f'{path!r} holds a model of dt = {info["dt"]:g} s; this '
                               f'learner samples at dt = {dt:g} s')
        held = 'feature_narx' if isinstance(ckpt.model, FeatureNarx) else 'nssm'
        if held != self.config.model_class:
            raise LearnerError(f'{path!r} holds a {held} model; this learner trains '
                               f'model_class {self.config.model_class}')
        return self._new_record(
            model=ckpt.model, params=ckpt.params, method=method, stage='meta',
            train_loss=float(info.get('train_loss', math.nan)),
            train_steps=int(info.get('train_steps', 0)),
            train_samples=int(info.get('train_samples', 0)), seed=int(info.get('seed', 0)))

    # --- source data ----------------------------------------------------------------------

    def _dt(self) -> float:
        """The sample time of this learner's models, s (the source systems', as resolved)."""
        return self.config.source.resolved().dt

    def _source_data(self) -> SourceData:
        if self._source is None:
            self._source = simulate_source(self.config.source)
        return self._source

    def _source_norm(self) -> Normalisation:
        """The normalisation of the source data (every model of this learner has it)."""
        return normalisation_from([t for ts in self._source_data().trajectories for t in ts])

    def _fresh_model(self) -> Nssm:
        """An NSSM of the node parameters with the source normalisation."""
        return Nssm(self.config.nssm, self._source_norm())

    # --- meta-training --------------------------------------------------------------------

    def meta_train(self, config: Union[MetaConfig, NarxMetaConfig], online: bool,
                   progress: Optional[ProgressFn] = None) -> MetaOutcome:
        """Algorithm 1 with `config`; with `online`, the closed-loop collector of eq. (ub).
        A :class:`NarxMetaConfig` meta-trains a feature NARX (:meth:`_meta_train_narx`).

        Raises:
            LearnerError: no usable source system.
            MetaTrainingError: too many non-finite tasks (from the core).
        """
        if isinstance(config, NarxMetaConfig):
            return self._meta_train_narx(config, progress)
        cfg = self.config
        model = self._fresh_model()
        try:
            source = SourceSet(self._source_data(), model.norm, cfg.nssm, cfg.train_fraction,
                               cfg.online_max_samples)
        except ValueError as err:
            raise LearnerError(f'source set: {err}') from None
        collector = (OnlineCollector(model, replace(cfg.online, seed=config.seed), cfg.source)
                     if online else None)
        result = meta_train(model, source, config, progress, collector)
        tail = [v for v in result.losses[-FINAL_LOSS_STEPS:] if math.isfinite(v)]
        final = float(np.mean(tail)) if tail else math.nan
        samples = (sum(samples_in(ts) for ts in self._source_data().trajectories)
                   + result.collected_samples)
        record = self._new_record(model=model, params=result.params, method=config.method,
                                  stage='meta', train_loss=final,
                                  train_steps=config.iterations, train_samples=samples,
                                  seed=config.seed, train_time=result.elapsed)
        return MetaOutcome(record, list(result.losses), final, result.skipped,
                           collector.stats if collector else None, result.collected_samples,
                           result.dropped_samples, result.elapsed)

    # --- adaptation -----------------------------------------------------------------------

    def _meta_for(self, method: str, model_class: str) -> ModelRecord:
        """The meta-model of `method` ('': the latest) of `model_class`."""
        metas = self.by_class.get(model_class, {})
        if not method:
            if model_class not in self.latest:
                raise LearnerError("no meta-model yet: call meta_train first (or start with "
                                   "meta_model_path), or adapt with 'supervised' or 'oracle'")
            method = self.latest[model_class]
        if method not in metas:
            have = ', '.join(sorted(metas)) or 'none'
            raise LearnerError(f"no {model_class} meta-model for method '{method}' (have: "
                               f"{have}): call meta_train with method '{method}' first")
        return metas[method]

    def _plant_source(self, plant: PlantDescription) -> SourceConfig:
        """The source settings with the target plant's dynamics, bounds and box."""
        return plant_source(self.config.source, plant.dt, plant.substeps, plant.u_min,
                            plant.u_max, plant.state_bound)

    def check_plant(self, plant: PlantDescription) -> None:
        """LearnerError unless the plant samples at the dt the source systems are simulated at
        (the plant's plant_info is the one source of truth for dt) and has the source
        family's numbers of inputs and outputs."""
        source = self.config.source
        if not math.isclose(plant.dt, source.dt, rel_tol=1e-9):
            raise LearnerError(f'dt: the plant samples at dt = {plant.dt} s, the source '
                               f'systems at dt = {source.dt} s: set dt:={plant.dt}')
        fam = source.plant_family
        if (len(plant.u_min), plant.n_y) != (fam.n_u, fam.n_y):
            raise LearnerError(f'family: the plant ({plant.family or "unnamed"}) has '
                               f'{len(plant.u_min)} input(s) and {plant.n_y} output(s), the '
                               f'source family {fam.name} {fam.n_u} and {fam.n_y}')

    def adapt(self, job: AdaptJob, samples: TargetSamples, plant: Optional[PlantDescription],
              progress: Optional[ProgressFn] = None) -> AdaptOutcome:
        """Adapt (or train a baseline) on the buffered target samples by
        :func:`~metampc_learner.target_fit.fit_target`; see the module.

        Raises:
            LearnerError: no such meta-model, too few samples, no or mismatching plant_info.
        """
        cfg = self.config
        if plant is not None:
            self.check_plant(plant)
        if job.method == ORACLE and (plant is None or not plant.theta):
            raise LearnerError("the oracle needs the target's theta: no plant_info received"
                               if plant is None else "the oracle needs the target's theta: "
                               'plant_info gives none (not a simulated plant)')
        model_class = job.model_class or cfg.model_class
        narx = model_class == 'feature_narx'
        if narx and job.method not in ('', *NARX_ADAPT_METHODS):
            methods = ('', *NARX_ADAPT_METHODS)
            raise LearnerError(f'model_class feature_narx adapts with '
                               f'{", ".join(repr(m) for m in methods)}, not {job.method!r}')
        model, start = (None, None) if narx else self._nssm_start(job.method)
        train, held, used = split_target(samples, job.n_samples, cfg.heldout_fraction,
                                         cfg.source.state_bound)
        if narx:
            self._check_narx_samples(samples, train, held, used)
            model = self._narx_start(job.method)
        fit_held = held             # the oracle's: simulated when the target's hold no window
        if job.method == ORACLE:
            train, fit_held = self._oracle_data(plant, model, held)
        elif not narx:
            self._check_nssm_samples(model, samples, train, held, used)
        try:
            fitted = fit_target(job.method, model, start, train, fit_held,
                                fit_settings(cfg, job), progress)
        except FitError as err:
            raise LearnerError(str(err)) from None
        record = self._new_record(
            model=fitted.model, params=fitted.result.params,
            method=job.method or self.latest[model_class], stage='adapted',
            train_loss=fitted.train_loss,
            train_steps=fitted.steps, train_samples=samples_in(train), seed=cfg.meta.seed,
            train_time=fitted.result.elapsed)
        return AdaptOutcome(record, fitted.result, used, samples_in(train), samples_in(held),
                            fitted.gain_check, fitted.replaced_by, fitted.rule)

    def _nssm_start(self, method: str) -> Tuple[Nssm, Optional[Params]]:
        """The NSSM a method fits (its architecture and normalisation) and the meta-model's
        weights it starts from (None for the baselines: a fresh NSSM of the node
        parameters)."""
        if method in BASELINES:
            return self._fresh_model(), None
        meta = self._meta_for(method, 'nssm')
        return meta.model, meta.params

    def _narx_start(self, method: str) -> FeatureNarx:
        """The feature NARX a method adapts: the meta-model of the method (the oracle: the
        latest); the arx's base: the latest meta-model, else a fresh one of the node
        parameters."""
        if method == ARX:
            if 'feature_narx' in self.latest:
                return self._meta_for('', 'feature_narx').model
            shape = self.config.narx
            return FeatureNarx(shape, self._source_norm(),
                               narx_init_params(shape, self.config.meta.seed))
        return self._meta_for('' if method == ORACLE else method, 'feature_narx').model

    def _check_nssm_samples(self, model: Nssm, samples: TargetSamples, train: List[Trajectory],
                            held: List[Trajectory], used: int) -> None:
        """LearnerError unless each part holds a window of H + T consecutive valid samples."""
        window = model.config.window
        if longest_run(train) >= window and longest_run(held) >= window:
            return
        cfg = self.config
        least = math.ceil(window / min(cfg.heldout_fraction, 1 - cfg.heldout_fraction))
        raise LearnerError(
            f'too few target samples: {len(samples)} buffered, {used} used, of which '
            f'{samples_in(train)} valid for training and {samples_in(held)} held out; '
            f'each part needs a run of H + T = {window} consecutive valid samples (about '
            f'{least} buffered samples in all without gaps); the longest runs are '
            f'{longest_run(train)} and {longest_run(held)} samples, broken by '
            f'{max(len(train) - 1, 0) + max(len(held) - 1, 0)} gap(s): steps that '
            'never reached the learner or left the state box')

    def _check_narx_samples(self, samples: TargetSamples, train: List[Trajectory],
                            held: List[Trajectory], used: int) -> None:
        """LearnerError unless the training part holds one-step equations and the held-out
        part a window of p + T samples (the feature NARX's)."""
        order = self.config.narx.order
        window = order + self.config.narx_meta.horizon
        if longest_run(train) <= order or longest_run(held) < window:
            raise LearnerError(
                f'too few target samples: {len(samples)} buffered, {used} used; the training '
                f'part needs a run of more than p = {order} consecutive valid samples, '
                f'the held-out part one of p + T = {window}; the longest runs are '
                f'{longest_run(train)} and {longest_run(held)} samples')

    def _oracle_data(self, plant: PlantDescription, model: Union[Nssm, FeatureNarx],
                     held: List[Trajectory]) -> Tuple[List[Trajectory], List[Trajectory]]:
        """The oracle's (training episodes, held-out trajectories): ``oracle_episodes``
        simulated episodes of the target's theta (a feature NARX: those longer than p), the
        target's held-out part, or where that holds no window of an NSSM fresh simulated
        episodes (seed + 1).

        Raises:
            LearnerError: every simulated episode left the state box.
        """
        cfg, seed, source = self.config, self.config.meta.seed, self._plant_source(plant)
        train = oracle_data(plant.theta, source, cfg.oracle.episodes, seed)
        if isinstance(model, FeatureNarx):
            train = [t for t in train if len(t) > model.shape.order]
            need = 1
        else:
            need = model.config.window
            if longest_run(held) < need:
                held = oracle_data(plant.theta, source, max(1, cfg.oracle.episodes // 5),
                                   seed + 1)
        if longest_run(train) < need:
            raise LearnerError(f'oracle: all {cfg.oracle.episodes} simulated episodes of '
                               f'theta = {list(plant.theta)} left the state box')
        return train, held

    # --- the feature NARX (model_class feature_narx) --------------------------------------

    def _meta_train_narx(self, config: NarxMetaConfig, progress: Optional[ProgressFn]
                         ) -> MetaOutcome:
        """The feature NARX's meta-training (:func:`narx_learning.meta_train`) on the source
        systems' trajectories, in the source normalisation; D_tr / D_test: each trajectory's
        halves in time."""
        data = self._source_data()
        systems = [[(t.u, t.y) for t in ts] for ts in data.trajectories if ts]
        if not systems:
            raise LearnerError('source set: no source system kept an episode')
        norm, start = self._source_norm(), time.monotonic()

        def report(iteration: int, loss: float) -> None:
            if progress is not None:
                progress(Progress(iteration, config.iterations, loss,
                                  time.monotonic() - start))

        try:
            result = narx_learning.meta_train(self.config.narx, norm, systems, config, report)
        except ValueError as err:
            raise LearnerError(f'feature NARX meta-training: {err}') from None
        final = float(np.mean(result.curve[-FINAL_LOSS_STEPS:]))
        model = FeatureNarx(self.config.narx, norm, result.params)
        record = self._new_record(
            model=model, params=model.params, method=config.method, stage='meta',
            train_loss=final, train_steps=config.iterations,
            train_samples=sum(samples_in(ts) for ts in data.trajectories), seed=config.seed,
            train_time=result.elapsed)
        return MetaOutcome(record, list(result.curve), final, 0, None, 0, 0, result.elapsed)

    def loop_adapt(self, version: int, samples: TargetSamples,
                   progress: Optional[ProgressFn] = None) -> AdaptOutcome:
        """Adaptation in the loop (``loop_adaptation``): eq. (infer) on `samples` (the latest
        window, all for training) from the model `version` in use, anchored to its method's
        meta-model; a model of stage 'online'. A feature NARX: its method's meta-model adapted
        in closed form on the window (:meth:`_loop_adapt_narx`).

        Raises:
            LearnerError: a version this learner did not make (or no longer keeps), or a
                window without a run of H + T consecutive valid samples.
        """
        cfg = self.config
        record = self.records.get(version)
        if record is None:
            raise LearnerError(f'model version {version} is not one of the last '
                               f'{KEPT_RECORDS} models of this learner')
        meta = self.by_class.get(record.model_class, {}).get(record.method)
        if isinstance(record.model, FeatureNarx):
            return self._loop_adapt_narx(record, meta, samples)
        # A model the gain check replaced by the ARX has the ARX's architecture: its own anchor.
        anchor = (meta.params if meta is not None and meta.model.config == record.model.config
                  else record.params)
        train, _, used = split_target(samples, 0, 0.0, cfg.source.state_bound)
        model = record.model
        train_w = Windows.from_trajectories(train, model.norm, model.config)
        if len(train_w) == 0:
            raise LearnerError(f'too few samples: the window holds {len(samples)}, its longest '
                               f'run of consecutive valid samples is {longest_run(train)}, a '
                               f'window needs H + T = {model.config.window}')
        loop = cfg.loop
        no_heldout = Windows.from_trajectories([], model.norm, model.config)
        steps = replace(cfg.adapt, steps=loop.steps, lr=loop.lr or cfg.adapt.lr,
                        gamma=loop.gamma)
        result = adapt(model, record.params, train_w, no_heldout, steps, progress,
                       anchor=anchor)
        new = self._new_record(model=model, params=result.params, method=record.method,
                               stage='online', train_loss=result.train_loss[-1],
                               train_steps=loop.steps, train_samples=samples_in(train),
                               seed=record.seed, train_time=result.elapsed)
        return AdaptOutcome(new, result, used, samples_in(train), 0)

    def _loop_adapt_narx(self, record: ModelRecord, meta: Optional[ModelRecord],
                         samples: TargetSamples) -> AdaptOutcome:
        """A feature NARX in the loop: ``narx_learning.adapt`` (a new head by the closed-form
        ridge toward the meta-model's at ``narx_gamma``, validated in time against the ARX;
        g the meta-model's) of the method's meta-model (none: the model in use) on the
        window. LearnerError: no one-step equation in the window."""
        start = time.monotonic()
        train, _, used = split_target(samples, 0, 0.0, self.config.source.state_bound)
        records = [(t.u, t.y) for t in train]
        base = (meta.model if meta is not None and isinstance(meta.model, FeatureNarx)
                else record.model)
        try:
            adapted = narx_learning.adapt(base, records, self.config.narx_meta.gamma)
        except ValueError as err:
            raise LearnerError(f'too few samples: the window holds {len(samples)}: {err}'
                               ) from None
        model = adapted.model
        loss = narx_learning.one_step_loss(model, records)
        result = AdaptResult(params=model.params, train_loss=[loss], heldout_loss=[],
                             elapsed=time.monotonic() - start)
        new = self._new_record(model=model, params=model.params, method=record.method,
                               stage='online', train_loss=loss, train_steps=1,
                               train_samples=samples_in(train), seed=record.seed,
                               train_time=result.elapsed)
        return AdaptOutcome(new, result, used, samples_in(train), 0, rule=adapted.rule)


__all__ = ['LearnerError', 'ModelRecord', 'MetaOutcome', 'AdaptOutcome', 'LearnerSession']
