"""Adaptation from a recording: a machine's bag or CSV, its mapping file, a meta-model checkpoint.

The usable grid samples (:mod:`.grid_samples`) are D_target: the first ``samples`` of them, the
last ``holdout`` share held out (``target_buffer.split_target``, cut at every skipped sample,
as the learner node splits its buffer). The learner's own fit runs on the rest
(``target_fit.fit_target``: eq. infer from the checkpoint's weights, supervised from random
weights of its architecture, or the ARX; with the gain check), settings resolved as the Adapt
service resolves a request; the result is saved as a learner checkpoint (stage 'adapted') and
a report says the T-step error on the held-out tail of the meta-model and of the model written,
the adaptation curve and the samples used and skipped. No rclpy. docs/offline_adaptation.md.
"""
import json
import math
import os
import time
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

import numpy as np
import torch

from metampc_model.feature_narx import FeatureNarx
from metampc_model.nssm import Nssm, Params
from metampc_plant.machine_mapping import load_mapping
from metampc_learner.adapt import GAUSS_NEWTON
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
from metampc_learner.data import longest_run, samples_in, Windows
from metampc_learner.grid_samples import grid_samples, GridSamples
from metampc_learner.heldout import heldout_loss
from metampc_learner.learner_params import (ADAPT, default_config, fit_settings,
                                            LearnerNodeConfig, resolve_adapt_request)
from metampc_learner.meta_train import META_METHODS
from metampc_learner.recorded_streams import read_streams
from metampc_learner.target_buffer import split_target, TargetSamples
from metampc_learner.target_fit import ARX, FitError, FitSettings, fit_target, SUPERVISED

STEP_KEYS = ('steps', 'lr', 'gamma')    # AdaptConfig's fields per method: adapt.<method>
RULE_KEYS = ('rule', 'cg_steps')        # and the learner node's: learner.adapt_<field>
NODE_KEYS = ('arx_order', 'gain_check')     # and its own
LISTED_RUNS = 50        # skipped runs listed in the report (all are counted)


class OfflineError(ValueError):
    """The inputs do not fit together (checkpoint and mapping, too few samples); one line."""


@dataclass
class Experiment:
    """What an experiment configuration says about adaptation, read by its own reader
    (``metampc_bringup.experiment_config``).

    Attributes:
        path: the file.
        learner: its learner node's configuration.
        requests: its Adapt request fields by method (``adapt.<method>`` under its protocol).
        learner_keys: the learner parameters the file sets.
    """

    path: str
    learner: LearnerNodeConfig
    requests: Mapping[str, Mapping[str, Any]]
    learner_keys: Tuple[str, ...] = ()


@dataclass
class OfflineConfig:
    """What to adapt and how.

    Attributes:
        method: '' (the checkpoint's), the checkpoint's meta method, 'supervised' or 'arx'
            (the checkpoint gives the architecture and the output scaling).
        steps, lr, gamma: of eq. (infer) (gamma: ignored by supervised; all: by arx); None: as
            the Adapt service resolves `experiment`'s request of the method (its
            ``adapt.<method>``, then its learner's adapt_<field>), else the learner's defaults.
        rule, cg_steps, arx_order: the step rule, a gauss_newton step's CG iterations, the
            ARX's order; None: `experiment`'s learner parameters (adapt_rule, adapt_cg_steps,
            arx_order), as the learner node runs that file, else the learner's defaults. The
            gain check (``gain_check``, on the family's tracked outputs) likewise.
        experiment: an experiment configuration's settings, or None.
        samples: use the first `samples` usable samples (0: all).
        holdout: the last share of them held out, in (0, 1).
        seed: the supervised baseline's initial weights (eq. infer is deterministic).
        keep_saturated: keep samples whose input is at a bound (clipped), see grid_samples.
        time_column: the CSV's time column (None: `time` if there is one, else one row per dt).
    """

    method: str = ''
    steps: Optional[int] = None
    lr: Optional[float] = None
    gamma: Optional[float] = None
    rule: Optional[str] = None
    cg_steps: Optional[int] = None
    arx_order: Optional[int] = None
    experiment: Optional[Experiment] = field(default=None, repr=False)
    samples: int = 0
    holdout: float = 0.2
    seed: int = 0
    keep_saturated: bool = False
    time_column: Optional[str] = None


def resolve_method(requested: str, info: Dict[str, Any], path: str) -> str:
    """The method of a run: the checkpoint's meta method, 'supervised' or 'arx' (OfflineError
    else)."""
    held = info.get('method', 'imaml')
    if requested in (SUPERVISED, ARX):
        return requested
    if held not in META_METHODS:
        raise OfflineError(f'{path} holds a {held!r} model, not a meta-model of '
                           f'{", ".join(META_METHODS)}: only --method {SUPERVISED} (from random '
                           f'weights of its architecture) or {ARX} trains on it')
    if requested not in ('', held):
        raise OfflineError(f'--method {requested}: {path} holds a {held} meta-model (use '
                           f'--method {held}, {SUPERVISED} or {ARX})')
    return held


def adapt_settings(method: str, config: OfflineConfig) -> Tuple[FitSettings, str]:
    """(the fit settings of `method`, where they come from): each given one, else as the Adapt
    service resolves `config.experiment`'s request of `method` on its learner configuration
    (``learner_params.resolve_adapt_request``, ``fit_settings``), else the learner's defaults.

    Raises:
        OfflineError: a value out of range (named).
    """
    experiment = config.experiment
    learner = experiment.learner if experiment else default_config()
    request = dict(experiment.requests.get(method, {})) if experiment else {}
    given = {k: getattr(config, k) for k in (*STEP_KEYS, *RULE_KEYS, 'arx_order')
             if getattr(config, k) is not None}
    try:
        job = resolve_adapt_request(SimpleNamespace(**{
            'steps': 0, 'lr': 0.0, 'gamma': 0.0, 'n_samples': 0, **request, 'method': method}),
            learner.adapt, learner.oracle)
        settings = fit_settings(learner, job)
        settings = replace(settings, seed=config.seed,
                           arx_order=given.get('arx_order', settings.arx_order),
                           adapt=replace(settings.adapt, **{k: v for k, v in given.items()
                                                            if k != 'arx_order'}))
        settings.adapt.validate()
    except ValueError as err:
        raise OfflineError(f'adaptation settings: {err}') from None
    names = {**{k: ADAPT.name(k) for k in RULE_KEYS}, **{k: k for k in NODE_KEYS}}
    listed = [k for k in STEP_KEYS if k in request] + [
        k for k, name in names.items() if experiment and name in experiment.learner_keys]
    where = ', '.join([f'{k} given' for k in given]
                      + [f'{k} from {experiment.path}' for k in listed if k not in given])
    return settings, where or 'the learner\'s defaults'


def _usable(grid: GridSamples) -> TargetSamples:
    keep = np.flatnonzero(grid.usable)
    return TargetSamples(keep.astype(np.int64), grid.u[keep], grid.y[keep])


def tstep_rmse(model: Nssm, params: Params, windows: Windows) -> List[float]:
    """Per output, the RMSE of the T-step predictions over all windows and steps, physical
    units (the normalised errors times y_std); NaN without windows."""
    if len(windows) == 0:
        return [math.nan] * model.config.n_y
    with torch.no_grad():
        y_hat = torch.func.functional_call(model, params, (windows.u, windows.y))
        err = (y_hat - windows.y[..., model.config.history:, :]).double()
    rms = err.square().mean(dim=(0, 1)).sqrt().numpy()
    return (rms * model.norm.y_std).tolist()


def _skipped_runs(grid: GridSamples) -> List[Dict[str, Any]]:
    return [{'from_step': a, 'to_step': b, 'from_time': float(grid.times[a]), 'count': b - a + 1,
             'reason': reason} for a, b, reason in grid.skipped_runs()[:LISTED_RUNS]]


def run_offline(recording: str, mapping_path: str, checkpoint: str, out: str,
                config: OfflineConfig, log: Callable[[str], None] = lambda text: None,
                progress: bool = False) -> Dict[str, Any]:
    """Adapt, write the checkpoint `out` and its report (`out` less .pt, + .json and .md).

    Returns the report (see docs/offline_adaptation.md). `log` gets a line per phase and per
    step; `progress`: a progress bar while a bag is read (on a terminal).

    Raises:
        MappingError, RecordingError, OfflineError (ValueError), OSError: one line each.
    """
    start = time.monotonic()
    mapping = load_mapping(mapping_path)
    ckpt = load_checkpoint(checkpoint)
    if isinstance(ckpt.model, FeatureNarx):
        raise OfflineError(f'{checkpoint}: a feature_narx model; offline adaptation is the '
                           "NSSM's (adapt it with the learner node, model_class feature_narx)")
    model, cfg = ckpt.model, ckpt.model.config
    n_u, n_y = len(mapping.command.inputs), len(mapping.outputs)
    if (cfg.n_u, cfg.n_y) != (n_u, n_y):
        raise OfflineError(f'{checkpoint}: a model of {cfg.n_u} input(s) and {cfg.n_y} '
                           f'output(s); the mapping {mapping_path} has {n_u} and {n_y}')
    if 'dt' in ckpt.info and not math.isclose(ckpt.info['dt'], mapping.dt, rel_tol=1e-9):
        raise OfflineError(f'{checkpoint}: a model of dt = {ckpt.info["dt"]:g} s; the mapping '
                           f'{mapping_path} samples at dt = {mapping.dt:g} s')
    method = resolve_method(config.method, ckpt.info, checkpoint)
    settings, settings_from = adapt_settings(method, config)
    recorded = read_streams(recording, mapping, config.time_column, progress)
    if recorded.cut_short:
        log(recorded.cut_short)
    grid = grid_samples(recorded, mapping, config.keep_saturated)
    usable = _usable(grid)
    log(f'{recording}: {len(grid.times)} samples on the grid of dt = {mapping.dt:g} s, '
        f'{len(usable)} usable')
    unreadable = {name: n for name, n in recorded.unreadable.items() if n}
    if unreadable:
        log(f'{recording}: unreadable (a mapped value that is no finite number): '
            + ', '.join(f'{n} of {recorded.read[name]} of {name}'
                        for name, n in unreadable.items()))
    if config.samples > len(usable):
        log(f'--samples {config.samples}: only {len(usable)} usable samples, all used')
    train, held, used = split_target(usable, config.samples, config.holdout, math.inf)
    dtype = next(iter(ckpt.params.values())).dtype
    train_w = Windows.from_trajectories(train, model.norm, cfg, dtype)
    held_w = Windows.from_trajectories(held, model.norm, cfg, dtype)
    if len(train_w) == 0 or len(held_w) == 0:
        raise OfflineError(
            f'too few usable samples: {used} used ({len(usable)} usable of {len(grid.times)}); '
            f'the longest runs without a skipped sample are {longest_run(train)} (training) and '
            f'{longest_run(held)} (held out), each part needs H + T = {cfg.window}')
    steps = settings.adapt
    if method == ARX:         # least squares, no steps: the settings do not apply
        steps, settings_from = replace(steps, steps=0), 'none (least squares)'
        log(f'{method}: ARX({settings.arx_order}) by least squares on {samples_in(train)} '
            f'samples, {len(held_w)} windows held out')
    else:
        said = steps_text(steps.steps, steps.lr, steps.rule, steps.cg_steps)
        log(f'{method}: {said} on {len(train_w)} windows, {len(held_w)} held out')

    def step_line(p):
        log(f'step {p.iteration}/{p.total}: held-out loss {p.loss:.5g} ({p.elapsed:.1f} s)')

    try:
        fitted = fit_target(method, model, None if method in (SUPERVISED, ARX) else ckpt.params,
                            train, held, settings, step_line)
    except FitError as err:
        raise OfflineError(str(err)) from None
    if fitted.gain_check:
        log(fitted.gain_check + ('; the ARX written in its place' if fitted.replaced_by else ''))
    written, result = fitted.model, fitted.result
    written_held = held_w if written is model else Windows.from_trajectories(
        held, written.norm, written.config, dtype)
    n_train, n_held = samples_in(train), samples_in(held)
    save_checkpoint(out, written, result.params, {
        'method': method, 'stage': 'adapted', 'train_loss': fitted.train_loss,
        'train_steps': fitted.steps, 'train_samples': n_train, 'seed': config.seed,
        'heldout_loss': fitted.heldout_loss, 'meta_checkpoint': checkpoint,
        'recording': recording, 'mapping': mapping_path, 'dt': mapping.dt})
    report = {
        'recording': recording, 'kind': recorded.kind, 'clock': recorded.clock,
        'cut_short': recorded.cut_short,
        'mapping': mapping_path, 'checkpoint': checkpoint, 'out': out, 'method': method,
        'steps': steps.steps, 'lr': steps.lr, 'rule': steps.rule, 'cg_steps': steps.cg_steps,
        'gamma': 0.0 if method in (SUPERVISED, ARX) else steps.gamma, 'seed': config.seed,
        'arx_order': settings.arx_order, 'settings_from': settings_from,
        'gain_check': fitted.gain_check, 'fallback': fitted.replaced_by,
        'history': cfg.history, 'loss_horizon': cfg.loss_horizon,
        'outputs': [o.name for o in mapping.outputs], 'units': [o.unit for o in mapping.outputs],
        'samples': {
            'dt': mapping.dt, 'first_time': float(grid.times[0]), 'grid': len(grid.times),
            'usable': len(usable), 'used': used, 'train': n_train, 'heldout': n_held,
            'unused': len(usable) - used, 'train_windows': len(train_w),
            'heldout_windows': len(held_w), 'skipped': grid.counts(),
            'skipped_runs': _skipped_runs(grid), 'messages': recorded.read,
            'unreadable': recorded.unreadable, 'keep_saturated': config.keep_saturated},
        'heldout': {
            'meta': {'loss': heldout_loss(model, ckpt.params, held_w),
                     'rmse': tstep_rmse(model, ckpt.params, held_w)},
            'adapted': {'loss': fitted.heldout_loss,
                        'rmse': tstep_rmse(written, result.params, written_held)}},
        'curve': {'train_loss': result.train_loss, 'heldout_loss': result.heldout_loss,
                  'rates': result.rates},
        'elapsed_s': time.monotonic() - start}
    stem = out[:-3] if out.endswith('.pt') else out
    with open(stem + '.json', 'w', encoding='utf-8') as f:
        json.dump(report, f, indent=2)
    with open(stem + '.md', 'w', encoding='utf-8') as f:
        f.write(report_markdown(report))
    return report


def steps_text(steps: int, lr: float, rule: str, cg_steps: int) -> str:
    """The steps of an adaptation in words, by its rule (AdaptConfig's fields)."""
    if rule == GAUSS_NEWTON:
        return f'{steps} Levenberg-Marquardt steps ({cg_steps} CG iterations each)'
    return f'{steps} steps at lr {lr:g}'


def report_markdown(report: Dict[str, Any]) -> str:
    """The report as a short markdown page (tables of the samples, the held-out error and the
    adaptation curve)."""
    s, h = report['samples'], report['heldout']
    lines = [f"# adapt_offline: {report['method']} on {os.path.basename(report['recording'])}",
             '', steps_text(report['steps'], report['lr'], report['rule'], report['cg_steps'])
             + f" (gamma {report['gamma']:g}) "
             f"from {report['checkpoint']}; H = {report['history']}, "
             f"T = {report['loss_horizon']}; written to {report['out']}.", '',
             *([f"**{report['cut_short']}.**", ''] if report['cut_short'] else []),
             *([f"**{report['gain_check']}: the ARX({report['arx_order']}) of the same samples "
                'is written in its place (the curve below is the adaptation\'s).**', '']
               if report['fallback'] else []),
             '| samples | count |', '|---|---|',
             f"| on the grid (dt = {s['dt']:g} s, from t = {s['first_time']:.3f} s) | "
             f"{s['grid']} |", f"| usable | {s['usable']} |",
             f"| used: training / held out | {s['train']} / {s['heldout']} |",
             f"| usable, beyond --samples | {s['unused']} |"]
    lines += [f'| skipped: {reason} | {n} |' for reason, n in s['skipped'].items() if n]
    lines += [f"| unreadable {name} (of {s['messages'][name]}, no finite number) | {n} |"
              for name, n in s['unreadable'].items() if n]
    lines += ['', f"| held-out T-step error (T = {report['loss_horizon']}, "
              f"{s['heldout_windows']} windows) | meta-model | adapted |", '|---|---|---|',
              f"| l_SSM (normalised) | {h['meta']['loss']:.5g} | {h['adapted']['loss']:.5g} |"]
    for name, unit, meta, ours in zip(report['outputs'], report['units'], h['meta']['rmse'],
                                      h['adapted']['rmse']):
        lines.append(f"| RMSE {name}{f' [{unit}]' if unit else ''} | {meta:.5g} | {ours:.5g} |")
    curve = report['curve']
    lines += ['', '| step | training loss | held-out loss |', '|---|---|---|']
    lines += [f'| {k} | {a:.5g} | {b:.5g} |'
              for k, (a, b) in enumerate(zip(curve['train_loss'], curve['heldout_loss']))]
    return '\n'.join(lines) + '\n'


__all__ = ['Experiment', 'OfflineConfig', 'OfflineError', 'adapt_settings', 'run_offline',
           'report_markdown', 'resolve_method', 'steps_text', 'tstep_rmse']
