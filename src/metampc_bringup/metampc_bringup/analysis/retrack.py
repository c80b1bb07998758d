"""Re-run the tracking runs of a run folder in one process, under other controller settings.

Each seed's recording holds the adapted models the experiment's controller flew. retrack
rebuilds, per seed and method, the controller core of the experiment (its controller section,
parsed as the node parses it) with parameter overrides (e.g. ``offset_free: off``), offers it
the recorded adapted model and runs the tracking episode against the plant core at theta*
(:mod:`metampc_controller.closed_loop`); the true-model NMPC runs the same episode as the
yardstick. Without overrides it reproduces the recorded tracking cost (a lockstep run is
deterministic), which :func:`retrack_seed` reports beside its own so that a reader can see it.

No ROS: seconds per seed instead of a graph's minutes, so controller designs can be compared
paired by seed on exactly the models an experiment produced.
"""
from dataclasses import asdict, dataclass, field
import math
import os
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import numpy as np

from metampc_bringup.analysis.paired_stats import paired_claim
from metampc_bringup.experiment_config import (experiment_method, ExperimentConfig,
                                               from_mapping)
from metampc_controller.closed_loop import Episode, Learner, run_episode
from metampc_controller.controller_core import build_model, ControllerCore
from metampc_controller.controller_params import ControllerConfig
from metampc_controller.controller_params import parse_params as parse_controller
from metampc_controller.controller_params import PARAMETERS as CONTROLLER_PARAMETERS
from metampc_controller.model_check import check
from metampc_model.predictor import NssmPredictor
from metampc_model.weights_codec import (DecodedNarx, DecodedWeights, fields_of,
                                         model_from_fields, weights_from_fields, WeightsError)
from metampc_plant.plant_description import PlantDescription
from metampc_plant.plant_params import parse_params as parse_plant
from metampc_plant.plant_params import PARAMETERS as PLANT_PARAMETERS
from metampc_plant.simulator import Plant, PlantConfig
from metampc_recording.recording_reader import read_recording

NSSM_WEIGHTS = 'metampc_msgs/msg/NssmWeights'


@dataclass
class MethodResult:
    """One method's tracking episode of one seed.

    Attributes:
        cost: tracking cost (the experiment's: squared errors of the tracked outputs).
        escaped: the plant diverged (the episode stopped there).
        rejected: why the model could not fly under these settings ('' if it flew).
        offsets: mean |y - r| of the tracked outputs over the last quarter of each set-point
            segment (the steady offset), one per segment.
    """

    cost: float
    escaped: bool
    rejected: str = ''
    offsets: List[float] = field(default_factory=list)


def adapted_models(recording: str, stage: str = 'adapted') -> Dict[str, Any]:
    """The last NssmWeights message of `stage` of each method in a recording, by the
    experiment's method name (a feature NARX beside an NSSM learner's: 'narx_<method>')."""
    rec = read_recording(recording)
    experiment = from_mapping(rec.run_config()['experiment'])
    learner_class = experiment.node_config('learner', experiment.first_seed).model_class
    topics = [t.name for t in rec.topics.values() if t.type_name == NSSM_WEIGHTS]
    out: Dict[str, Any] = {}
    for _, _, msg in rec.decoded(topics):
        if msg.stage == stage:
            out[experiment_method(msg.method, msg.model_class, learner_class)] = msg
    return out


def check_verdicts(experiment: ExperimentConfig, seed: int, recording: str,
                   episode: Episode) -> Dict[str, Dict[str, Any]]:
    """What model_check says of each recorded adapted NSSM on `episode`'s samples (e.g. the
    NMPC's tracking run of the seed, which a controller holds when the adapted models come):
    against its own meta-model (an update of it) and against persistence (a first model)."""
    config = controller_config(experiment.resolved(), seed, {})
    metas = adapted_models(recording, 'meta')

    def verdict(new: NssmPredictor, against: Optional[NssmPredictor]) -> Dict[str, Any]:
        v = check(new, against, episode.u, episode.y, config.mpc, config.model_check)
        return {**asdict(v), 'reason': v.reason()}
    out = {}
    for method, msg in adapted_models(recording).items():
        if msg.model_class == 'feature_narx':     # the check is the latent MPC's, an NSSM's
            continue
        new, meta = _predictor(msg), metas.get(method)
        out[method] = {'vs_meta': verdict(new, _predictor(meta)) if meta is not None else None,
                       'vs_persistence': verdict(new, None)}
    return out


def _predictor(msg) -> NssmPredictor:
    decoded = weights_from_fields(fields_of(msg))
    return NssmPredictor(decoded.config, decoded.norm, decoded.params)


def controller_values(experiment: ExperimentConfig, seed: int, overrides: Mapping[str, Any]
                      ) -> Dict[str, Any]:
    """The controller node's parameter values of the experiment's run `seed`, with
    `overrides` on top."""
    return {**experiment.node_parameters('controller', seed), **overrides}


def controller_config(experiment: ExperimentConfig, seed: int, overrides: Mapping[str, Any]
                      ) -> ControllerConfig:
    """The controller's configuration of `seed` with parameter `overrides`, checked as the
    node checks it (ParameterError naming the parameter)."""
    return controller_settings(controller_values(experiment, seed, overrides))


def controller_settings(values: Mapping[str, Any]) -> ControllerConfig:
    """The controller's configuration of its parameter `values` (a run's controller section),
    its declared defaults filled in, checked as the node checks it."""
    return parse_controller(_with_defaults(CONTROLLER_PARAMETERS, values))


def plant_config(plant: Mapping[str, Any], theta: Sequence[float]) -> PlantConfig:
    """The plant core's settings from the plant node's parameter values `plant` (its declared
    defaults filled in) at `theta`, checked as the node checks them."""
    return parse_plant(_with_defaults(PLANT_PARAMETERS, {**plant, 'theta': list(theta)})).plant


def fly(controller: Mapping[str, Any], plant: Mapping[str, Any], theta: Sequence[float],
        x0: Sequence[float], steps: int,
        weights: Optional[Union[DecodedWeights, DecodedNarx]] = None,
        learner: Optional[Learner] = None) -> Episode:
    """One tracking episode in one process (no ROS): the controller node's parameter values
    `controller` (its declared defaults filled in), its latent MPC on `weights` (a feature
    NARX's: relinearised each tick) or, with
    None, its true-model NMPC, against the plant core of the plant node's parameter values
    `plant` at `theta`, from `x0` for `steps` samples (:func:`closed_loop.run_episode`, whose
    `learner` answers adaptation requests).

    Raises:
        WeightsError: the controller rejects the weights (one line).
    """
    values = _with_defaults(CONTROLLER_PARAMETERS, controller)
    values.update(planner='nmpc' if weights is None else 'latent_mpc', active=True)
    core = ControllerCore(parse_controller(values))
    plant_cfg = plant_config(plant, theta)
    core.set_plant(PlantDescription(plant_cfg.family, plant_cfg.dt,
                                    plant_cfg.u_min, plant_cfg.u_max, core.n_y, True))
    if weights is not None:
        core.offer(build_model(weights, 1, 'retrack', 'adapted', core.config.mpc, core.n_u,
                               core.n_y, core.config.history))
    return run_episode(core, Plant(plant_cfg), steps, theta, x0, learner=learner)


def _with_defaults(table: Mapping[str, Any], values: Mapping[str, Any]) -> Dict[str, Any]:
    """A node's parameter values: the declared defaults, then `values` (as the node sees them)."""
    out = {name: spec.default for name, spec in table.items()}
    out.update(values)
    return out


def segment_offsets(y: np.ndarray, ref: np.ndarray, tracked: List[int], preview: int
                    ) -> List[float]:
    """Steady offset per constant-reference segment: mean |y - r| over the last quarter of
    the part of the segment before the next set-point enters the MPC's horizon (`preview`
    samples: a planner that sees the step coming leaves the old set-point early, which is
    not an offset). y, ref: (K, n_y) aligned; tracked columns."""
    r = ref[:, tracked]
    change = np.flatnonzero(np.any(np.diff(r, axis=0) != 0, axis=1)) + 1
    ends = np.r_[change - preview, len(r)]
    starts = np.r_[0, change]
    out = []
    for a, b in zip(starts, ends):
        if b - a >= 4:
            tail = slice(b - (b - a) // 4, b)
            out.append(float(np.mean(np.abs(y[tail][:, tracked] - r[tail]))))
    return out


def retrack_seed(experiment: ExperimentConfig, seed: int, recording: str,
                 overrides: Mapping[str, Any], methods: Optional[List[str]] = None,
                 nmpc: bool = True, episodes: Optional[Dict[str, Episode]] = None
                 ) -> Dict[str, MethodResult]:
    """Tracking of every recorded adapted model (or `methods`) of one seed, plus 'nmpc' (the
    yardstick: unaffected by the latent MPC's settings, and the slowest part; `nmpc` False
    leaves it out). `episodes`, if given, receives each method's :class:`Episode`."""
    models = adapted_models(recording)
    wanted = methods if methods is not None else sorted(models)
    flown: Dict[str, Optional[Union[DecodedWeights, DecodedNarx]]] = {
        method: model_from_fields(fields_of(models[method]))
        for method in wanted if method in models}
    if nmpc:
        flown['nmpc'] = None
    return track_models(experiment, seed, overrides, flown, episodes)


def track_models(experiment: ExperimentConfig, seed: int, overrides: Mapping[str, Any],
                 models: Mapping[str, Optional[Union[DecodedWeights, DecodedNarx]]],
                 episodes: Optional[Dict[str, Episode]] = None) -> Dict[str, MethodResult]:
    """The experiment's tracking run of `seed` (its theta*, track_x0, reference, controller
    section with `overrides`) flown by each of `models` in turn: the latent MPC on the
    weights, or the true-model NMPC for None. `episodes`, if given, receives each
    :class:`Episode`."""
    cfg = experiment.resolved()
    controller = controller_values(cfg, seed, overrides)
    plant = cfg.node_parameters('plant', seed)
    horizon = controller_config(cfg, seed, overrides).mpc.horizon
    theta = cfg.target_theta(seed)
    tracked = list(cfg.tracked_outputs)
    results: Dict[str, MethodResult] = {}
    for method, weights in models.items():
        try:
            episode = fly(controller, plant, theta, cfg.track_x0, cfg.track_steps(), weights)
        except WeightsError as err:
            results[method] = MethodResult(float('nan'), False, rejected=str(err))
            continue
        if episodes is not None:
            episodes[method] = episode
        results[method] = MethodResult(
            cost=episode.tracking_cost(tracked), escaped=episode.escaped_at is not None,
            offsets=segment_offsets(episode.y[1:], episode.y_ref, tracked, horizon))
    return results


def seed_recordings(run_dir: str) -> Dict[int, str]:
    """{seed: recording path} of a run folder (seed_<n>/recording.mcap)."""
    out = {}
    for name in sorted(os.listdir(run_dir)):
        path = os.path.join(run_dir, name, 'recording.mcap')
        if name.startswith('seed_') and name[5:].isdigit() and os.path.exists(path):
            out[int(name[5:])] = path
    return out


def summarise(per_seed: Mapping[int, Mapping[str, Mapping[str, dict]]]) -> Dict[str, Any]:
    """Per variant and method: tracking cost / NMPC by seed (inf: escaped), median, worst,
    escapes, refusals, mean steady offset by seed; and, for every variant after the first,
    the paired claim "variant < first variant" on the cost ratios (log ratios, Wilcoxon;
    :func:`paired_claim`).

    per_seed: {seed: {variant: {method: MethodResult as a dict}}}, every variant's dict
    holding 'nmpc' or the first variant's does.
    """
    table: Dict[str, Dict[str, Dict[str, Any]]] = {}
    for seed in sorted(per_seed):
        variants = per_seed[seed]
        nmpc = next(v['nmpc']['cost'] for v in variants.values() if 'nmpc' in v)
        for name, results in variants.items():
            for method, r in results.items():
                if method == 'nmpc':
                    continue
                row = table.setdefault(name, {}).setdefault(method, {
                    'ratios': {}, 'offsets': {}, 'escapes': 0, 'rejected': 0})
                row['ratios'][seed] = math.inf if r['escaped'] else r['cost'] / nmpc
                row['escapes'] += int(r['escaped'])
                row['rejected'] += int(bool(r['rejected']))
                row['offsets'][seed] = (float(np.mean(r['offsets'])) if r['offsets']
                                        else math.nan)
    first = next(iter(table), None)
    for name, methods in table.items():
        for method, row in methods.items():
            ratios = np.array(list(row['ratios'].values()))
            offsets = np.array(list(row['offsets'].values()))
            row.update(median=float(np.median(ratios)), worst=float(np.max(ratios)),
                       mean_offset=float(np.nanmean(offsets)) if np.isfinite(offsets).any()
                       else math.nan)
            base = table[first].get(method)
            if name != first and base is not None:
                seeds = sorted(set(row['ratios']) & set(base['ratios']))
                row['vs_' + first] = paired_claim([row['ratios'][s] for s in seeds],
                                                  [base['ratios'][s] for s in seeds], log=True)
    return table
