"""The Cascaded Tanks benchmark run: every seed's fits, the twin's tracking, the summary.

:func:`run` checks the options, fits the grey-box to all 1024 estimation samples (the twin:
the family at that fit), flies the true-model NMPC on the twin once, then per seed the fits of
:mod:`.cascaded_tanks` (OUT/seed_<s>/benchmark.json, the series in series.npz) and the
tracking of each fitted NSSM on the twin by the latent MPC of the config's controller section,
and the feature NARX rows of :mod:`.cascaded_tanks_narx`; it writes OUT/summary.json and the
figures. Every step is cached in OUT (the same options again resume). No ROS.
"""
import dataclasses
import json
import os
import time
from typing import Dict, Tuple

import numpy as np
import torch

from metampc_bringup.analysis.cascaded_tanks_report import figure, summary, twin_figure
from metampc_bringup.analysis.twin import track_twin
from metampc_bringup.experiment_config import ConfigError, ExperimentConfig, \
    learner_config, load
from metampc_bringup.studies.cascaded_tanks import fit_all, FITS, greybox, log, META, \
    meta_models, TAIL, TanksOptions
from metampc_bringup.studies.cascaded_tanks_narx import narx_rows
from metampc_bringup.studies.json_cache import cached, save
from metampc_learner.learner_params import AdaptJob, fit_settings
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.cascaded_tanks_data import load_cascaded_tanks
from metampc_plant.identification.validation import Protocol
from metampc_plant.registry import get_family


def series(episode) -> Dict[str, np.ndarray]:
    """A tracking run's level y (K + 1,), pump voltage u (K + 1,) and reference (K,), V."""
    return {'y': episode.y[:, 0], 'u': episode.u[:, 0], 'y_ref': episode.y_ref[:, 0]}


def twin_nmpc(options: TanksOptions, experiment, grey: dict
              ) -> Tuple[dict, Dict[str, np.ndarray]]:
    """The true-model NMPC's run on the twin, the same for every seed (OUT/twin_nmpc.json when
    it holds this twin and experiment, else flown and saved there): its result and series."""
    path = os.path.join(options.out, 'twin_nmpc.json')
    wanted = {'theta': grey['theta'], 'x0': grey['x0'],
              'experiment': json.dumps(experiment.to_dict(), sort_keys=True)}
    found = cached(path, wanted)
    if found is None:
        log('twin: the NMPC\'s tracking run')
        episodes: dict = {}
        result = track_twin(experiment, grey['theta'], grey['x0'], {'nmpc': None}, episodes)
        found = {**wanted, 'result': dataclasses.asdict(result['nmpc']),
                 'series': {k: v.tolist() for k, v in series(episodes['nmpc']).items()}}
        save(path, found)
    return found['result'], {k: np.array(v) for k, v in found['series'].items()}


def twin(experiment, grey: dict, fitted: Dict[str, DecodedWeights], nmpc: dict
         ) -> Tuple[Dict[str, Dict[str, dict]], Dict[str, Dict[str, np.ndarray]]]:
    """Each fitted NSSM's tracking run on the twin: {'fit <n>': {'nmpc': nmpc, method: its
    result}} and each run's series ('<method> <n>')."""
    episodes: dict = {}
    results = track_twin(experiment, grey['theta'], grey['x0'], fitted, episodes)
    out: Dict[str, Dict[str, dict]] = {}
    for name, result in results.items():
        method, n = name.split()
        out.setdefault(f'fit {n}', {'nmpc': nmpc})[method] = dataclasses.asdict(result)
        log(f'twin, {name}: tracking cost {result.cost:.4g} (NMPC {nmpc["cost"]:.4g})'
            f'{", escaped" if result.escaped else ""}{", refused" if result.rejected else ""}')
    return out, {name: series(ep) for name, ep in episodes.items()}


def run_seed(options: TanksOptions, experiment, seed: int, data, protocol: Protocol,
             grey: dict, nmpc: dict) -> dict:
    """One seed's meta-training, fits, test-record figures and twin runs: OUT/seed_<s>/
    benchmark.json (and the series in series.npz there) when it holds this run's settings,
    else computed (meta-models cached there too)."""
    folder = os.path.join(options.out, f'seed_{seed}')
    path = os.path.join(folder, 'benchmark.json')
    wanted = {'seed': seed, 'config': options.config, 'max_steps': options.max_steps,
              'meta_iterations': options.meta_iterations, 'n_systems': options.n_systems,
              'greybox': grey, 'nmpc': nmpc,
              'experiment': json.dumps(experiment.to_dict(), sort_keys=True)}
    found = cached(path, wanted)
    if found is not None and os.path.exists(os.path.join(folder, 'series.npz')):
        log(f'seed {seed}: cached in {path}')
        return found
    os.makedirs(folder, exist_ok=True)
    torch.manual_seed(seed)
    start = time.monotonic()
    model, meta, meta_info = meta_models(options, experiment, seed, folder)
    settings = fit_settings(learner_config(experiment, seed), AdaptJob('', 0, 1.0, 0.0, 0))
    rows, sims, fitted = fit_all(options, seed, model, meta, get_family('cascaded_tanks'), data,
                                 protocol, settings)
    twin_rows, twin_series = twin(experiment, grey, fitted, nmpc)
    np.savez_compressed(os.path.join(folder, 'series.npz'), **{
        f'test {k}': v for k, v in sims.items()}, **{
        f'twin {k} {part}': v for k, s in twin_series.items() for part, v in s.items()})
    report = {**wanted, 'meta': meta_info, 'rows': rows, 'twin': twin_rows,
              'scored': f'test samples {model.config.history + 1}..1023',
              'wall_s': round(time.monotonic() - start, 1)}
    save(path, report)
    return report


class BadOptions(ValueError):
    """Options the benchmark cannot run with (one line, exit 2)."""


def checked(options: TanksOptions) -> Tuple[ExperimentConfig, Protocol]:
    """The experiment of --config and the grey-box protocol, the options checked.

    Raises:
        BadOptions: not the cascaded_tanks family, a negative number, a seed twice, an --out
            that is a file, or a config or protocol that cannot run (the message says which).
    """
    try:
        experiment = load(options.config)
        if experiment.plant_family.name != 'cascaded_tanks':
            raise ConfigError(f'--config {options.config}: family '
                              f'{experiment.plant_family.name}, not cascaded_tanks')
        if min(*options.seeds, options.max_steps, options.meta_iterations,
               options.n_systems) < 0:
            raise ConfigError('--seed, --max-steps, --meta-iterations, --n-systems must be >= 0')
        if len(set(options.seeds)) != len(options.seeds):
            raise ConfigError(f'--seed: each seed once, got {list(options.seeds)}')
        if os.path.exists(options.out) and not os.path.isdir(options.out):
            raise ConfigError(f'--out {options.out} exists and is not a folder')
        # The grey-box search's candidates are drawn with rng(0) whatever the seed: ARX and
        # grey-box do not depend on it.
        protocol = Protocol(fit_samples=300, validation_start=TAIL,
                            candidates=options.candidates, polish=options.polish,
                            substeps=options.substeps, seed=0)
        protocol.check(1024)
    except ValueError as err:       # ConfigError is one
        raise BadOptions(str(err)) from err
    return experiment, protocol


def run(options: TanksOptions) -> dict:
    """The whole benchmark (cached in options.out): the summary over the seeds (saved in
    OUT/summary.json), the figures drawn where the options name them.

    Raises:
        BadOptions: see :func:`checked` (nothing run).
        OutOfRange: a grey-box fit left the family's parameter range.
    """
    experiment, protocol = checked(options)
    os.makedirs(options.out, exist_ok=True)
    torch.set_num_threads(1)
    data = load_cascaded_tanks()
    # The twin: the family at the grey-box fit to the whole estimation record.
    grey = greybox(options, get_family('cascaded_tanks'), data.u_est, data.y_est, FITS[-1],
                   protocol)
    nmpc, nmpc_series = twin_nmpc(options, experiment, grey)
    reports = [run_seed(options, experiment, seed, data, protocol, grey, nmpc)
               for seed in options.seeds]
    for report in reports:
        report['rows'] = report['rows'] + narx_rows(options, experiment, report['seed'], data)
    result = summary(reports, nmpc)
    save(os.path.join(options.out, 'summary.json'), result)
    if options.figure or options.twin_figure:
        first = np.load(os.path.join(options.out, f'seed_{options.seeds[0]}', 'series.npz'))
        if options.figure:
            figure(options.figure, data.y_test, first, data.ts, FITS, META)
        if options.twin_figure:
            twin_figure(options.twin_figure, options.seeds[0], first, nmpc_series, data.ts,
                        FITS, META)
    return result
