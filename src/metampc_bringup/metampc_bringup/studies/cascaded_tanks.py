"""The Cascaded Tanks benchmark's fits on the estimation record, scored on the test record.

Its options (:class:`TanksOptions`, the script's flags) and protocol (FITS, CHOOSE_HEAD, TAIL,
LRS). Per meta-training seed, :func:`meta_models` meta-trains iMAML and first-order MAML on the
family's simulated systems (cached); :func:`fit_all` fits every model on each of FITS (the
meta-models adapted by eq. (infer), the supervised NSSM, ARX, the grey-box of
:func:`greybox`, cached), each choice (step size, steps, ARX orders) made on the estimation
record, and scores each on the test record once: free-run simulation and T-step prediction
RMSE, volts. docs/real_data.md has the figures. No ROS.
"""
import dataclasses
import json
import math
import os
import sys
import time
from typing import Dict, List, Tuple

import numpy as np

from metampc_bringup.analysis.nssm_records import record_windows, simulate_nssm, trajectory
from metampc_bringup.analysis.twin import nssm_weights
from metampc_bringup.experiment_config import learner_config
from metampc_bringup.studies.json_cache import cached, save
from metampc_bringup.studies.learning_setup import request_meta_config
from metampc_learner.adapt import AdaptConfig
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
from metampc_learner.data import normalisation_from, simulate_source, SourceSet, Trajectory
from metampc_learner.meta_train import meta_train
from metampc_learner.offline_adaptation import tstep_rmse
from metampc_learner.target_fit import fit_target, FitSettings, TargetFit
from metampc_model.nssm import Nssm, Params
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.families.cascaded_tanks import GUESS
from metampc_plant.identification.arx import fit_arx, predict_arx, simulate_arx
from metampc_plant.identification.greybox import predict_greybox, simulate_family
from metampc_plant.identification.validation import arx_baseline, fit_greybox_head, Protocol, \
    rmse

META = ('imaml', 'maml')       # the meta methods this benchmark compares (of META_METHODS)
FITS = (300, 1024)           # estimation samples 0..n-1 fitted
CHOOSE_HEAD = {300: 300, 1024: 768}   # head that the choices of each fit are made on
TAIL = 768                   # estimation samples TAIL..1023 score the choices
LRS = (0.03, 0.1, 0.3, 1.0)  # adaptation step sizes tried (the learner's Armijo maximum)


@dataclasses.dataclass(frozen=True)
class TanksOptions:
    """The benchmark's options, one field a flag of scripts/cascaded_tanks_benchmark.py
    (--seed is `seeds`; the flags' help says what each means)."""
    out: str
    seeds: Tuple[int, ...] = (0,)
    config: str = 'config/cascaded_tanks.yaml'
    figure: str = ''
    twin_figure: str = ''
    max_steps: int = 200
    meta_iterations: int = 0
    n_systems: int = 0
    candidates: int = 512
    polish: int = 4
    substeps: int = 4


def log(text: str) -> None:
    """`text` on stderr after the time of day, [HH:MM:SS]."""
    print(f'[{time.strftime("%H:%M:%S")}] {text}', file=sys.stderr, flush=True)


def run_adaptation(model: Nssm, init: Params, method: str, train: Trajectory,
                   held: Trajectory, lr: float, steps: int, settings: FitSettings) -> TargetFit:
    """eq. (infer) from the meta-model `init`, or the supervised NSSM from
    init_params(settings.seed), `steps` plain steps at `lr` (``target_fit.fit_target``, with
    --config's gain check)."""
    return fit_target(method, model, init, [train], [held],
                      dataclasses.replace(settings, adapt=AdaptConfig(steps=steps, lr=lr)))


def choose_adaptation(model: Nssm, init: Params, method: str, train: Trajectory,
                      held: Trajectory, max_steps: int, settings: FitSettings
                      ) -> Dict[str, float]:
    """The step size of LRS and the steps (0..max_steps) of least held-out loss, with it."""
    best = {'lr': LRS[0], 'steps': 0, 'heldout_loss': math.inf}
    for lr in LRS:
        try:
            curve = run_adaptation(model, init, method, train, held, lr, max_steps,
                                   settings).result.heldout_loss
        except ValueError:      # the loss turned non-finite: this step size is out
            continue
        k = int(np.nanargmin(curve))
        if curve[k] < best['heldout_loss']:
            best = {'lr': lr, 'steps': k, 'heldout_loss': float(curve[k])}
    return best


def meta_models(options: TanksOptions, experiment, seed: int, folder: str
                ) -> Tuple[Nssm, Dict[str, Params], Dict[str, dict]]:
    """The meta-model of each method: folder/meta_<method>.pt when it holds this run's
    settings, else meta-trained on the family's simulated source set (and saved there)."""
    cfg = learner_config(experiment, seed)
    source_cfg = dataclasses.replace(cfg.source, seed=seed, **(
        {'n_systems': options.n_systems} if options.n_systems else {}))
    model, params, info = None, {}, {}
    source = None
    for method in META:
        meta = dataclasses.replace(cfg.meta, method=method, seed=seed,
                                   **request_meta_config(experiment, method))
        if options.meta_iterations:
            meta = dataclasses.replace(meta, iterations=options.meta_iterations)
        wanted = {'method': method, 'seed': seed, 'config': options.config,
                  'meta_config': json.dumps(dataclasses.asdict(meta), sort_keys=True),
                  'source_config': repr(source_cfg)}
        path = os.path.join(folder, f'meta_{method}.pt')
        if os.path.exists(path):
            ckpt = load_checkpoint(path)
            if all(ckpt.info.get(k) == v for k, v in wanted.items()):
                log(f'{method}: meta-model cached in {path}')
                model, params[method], info[method] = ckpt.model, ckpt.params, ckpt.info
                continue
        if source is None:
            log(f'simulating {source_cfg.n_systems} source systems of {source_cfg.family}')
            data = simulate_source(source_cfg)
            model = Nssm(cfg.nssm, normalisation_from(
                [t for ts in data.trajectories for t in ts]))
            source = SourceSet(data, model.norm, cfg.nssm, cfg.train_fraction)
        log(f'{method}: meta-training, {meta.iterations} outer steps')

        def progress(p, method=method):
            if p.iteration % max(1, p.total // 10) == 0:
                log(f'{method}: step {p.iteration}/{p.total}, meta-test loss {p.loss:.4g} '
                    f'({p.elapsed:.0f} s)')

        result = meta_train(model, source, meta, progress)
        info[method] = {**wanted, 'stage': 'meta', 'seconds': round(result.elapsed, 1),
                        'final_loss': float(np.mean(result.losses[-10:])),
                        'best_iteration': result.best_iteration}
        params[method] = result.params
        save_checkpoint(path, model, result.params, info[method])
    return model, params, info


class OutOfRange(ValueError):
    """A grey-box fit outside the family's parameter range (one line, exit 2)."""


def greybox(options: TanksOptions, family, u: np.ndarray, y: np.ndarray, n: int,
            protocol: Protocol) -> dict:
    """The grey-box fit to estimation samples 0..n-1 (cached in OUT/greybox_<n>.json).

    Raises:
        OutOfRange: the fit left the family's parameter range (the twin of such a theta is not
            a member of the family): not cached, so a better budget fits again; a cached fit
            out of the range is fitted again too.
    """
    path = os.path.join(options.out, f'greybox_{n}.json')
    wanted = {'n': n, 'candidates': protocol.candidates, 'polish': protocol.polish,
              'substeps': protocol.substeps}
    found = cached(path, wanted)
    if found is not None and _in_range(family, found['theta']):
        log(f'grey-box on 0..{n - 1}: cached in {path}')
        return found
    log(f'grey-box on 0..{n - 1}: fitting')
    start = time.monotonic()
    fit = fit_greybox_head(family, u, y, n, protocol, GUESS,
                           (np.zeros(family.n_theta), np.full(family.n_theta, np.inf)))
    if not _in_range(family, fit.theta):
        raise OutOfRange(f'the grey-box fit on 0..{n - 1} ({protocol.candidates} candidates, '
                         f'polish {protocol.polish}) left the family\'s parameter range: '
                         f'theta {np.round(fit.theta, 5).tolist()}, support '
                         f'{[c.support for c in family.theta]}; try more --candidates or '
                         f'--polish')
    out = {**wanted, 'theta': fit.theta.tolist(), 'x0': fit.x0.tolist(), 'fit_rmse': fit.rmse,
           'seconds': round(time.monotonic() - start, 1)}
    save(path, out)
    return out


def _in_range(family, theta) -> bool:
    """theta within the family's prior support (check_theta_in_support)."""
    try:
        family.check_theta_in_support(theta)
    except ValueError:
        return False
    return True


def scores(y: np.ndarray, y_sim: np.ndarray, predicted: np.ndarray, origins: np.ndarray,
           horizon: int, first: int) -> Dict[str, float]:
    """Simulation RMSE on samples first..N-1, T-step prediction RMSE at `origins`."""
    measured = y[origins[:, None] + np.arange(1, horizon + 1)]
    return {'simulation_rmse': rmse(y_sim[first:], y[first:]),
            'prediction_rmse': rmse(predicted, measured)}


def fit_all(options: TanksOptions, seed: int, model, meta, family, data, protocol,
            settings: FitSettings
            ) -> Tuple[List[dict], Dict[str, np.ndarray], Dict[str, DecodedWeights]]:
    """Every model fitted on each of FITS, scored on the test record once; the simulations
    ('<model> <n>': (1024,)); the fitted NSSMs ('<method> <n>'; the ARX where the gain check
    refused one)."""
    u, y, ut, yt = data.u_est, data.y_est, data.u_test, data.y_test
    n_h, n_t = model.config.history, model.config.loss_horizon
    origins = np.arange(n_h, len(yt) - n_t)      # the NSSM's windows on the test record
    test_w = record_windows(model, ut, yt, 0, len(yt))
    held = trajectory(u, y, TAIL - 1 - n_h, len(y))
    rows, sims, fitted = [], {}, {}
    for n in FITS:
        head = CHOOSE_HEAD[n]
        for method in (*META, 'supervised'):
            start = time.monotonic()
            chosen = choose_adaptation(model, meta.get(method), method,
                                       trajectory(u, y, 0, head), held, options.max_steps,
                                       settings)
            fit = run_adaptation(model, meta.get(method), method, trajectory(u, y, 0, n), held,
                                 chosen['lr'], chosen['steps'], settings)
            flown, params = fit.model, fit.result.params
            sim = simulate_nssm(flown, params, ut, yt)
            row = {'fit': n, 'model': method, 'choice': chosen,
                   'validation_sim_rmse': rmse(simulate_nssm(flown, params, u, y)[TAIL:],
                                               y[TAIL:]) if n < TAIL else None,
                   'test': {'simulation_rmse': rmse(sim[n_h + 1:], yt[n_h + 1:]),
                            'prediction_rmse': tstep_rmse(flown, params, test_w if flown is model
                                                          else record_windows(flown, ut, yt, 0,
                                                                              len(yt)))[0]},
                   'seconds': round(time.monotonic() - start, 1)}
            rows.append(row)
            sims[f'{method} {n}'] = sim
            fitted[f'{method} {n}'] = nssm_weights(flown, params)
            log(f'{method} on 0..{n - 1}: lr {chosen["lr"]:g}, {chosen["steps"]} steps; test '
                f'simulation RMSE {row["test"]["simulation_rmse"]:.4f} V')
        arx, _ = arx_baseline(u, y, dataclasses.replace(protocol, fit_samples=head))
        arx = fit_arx(u[:n], y[:n], len(arx.a), len(arx.b), arx.nk)
        sim = simulate_arx(arx, ut, yt)
        rows.append({'fit': n, 'model': f'ARX({len(arx.a)}, {len(arx.b)}, {arx.nk})',
                     'test': scores(yt, sim, predict_arx(arx, ut, yt, origins, n_t), origins,
                                    n_t, n_h + 1),
                     'test_all_samples': rmse(sim[arx.lag:], yt[arx.lag:])})
        sims[f'ARX {n}'] = sim
        grey = greybox(options, family, u, y, n, protocol)
        x_sim, y_sim = simulate_family(family, np.array([grey['theta']]), np.array([grey['x0']]),
                                       ut[:, None], protocol.substeps)
        predicted = predict_greybox(family, grey['theta'], ut[:, None], yt[:, None], origins,
                                    n_h, n_t, x_sim[0], protocol.substeps)[..., 0]
        rows.append({'fit': n, 'model': 'grey-box', 'theta': grey['theta'], 'x0': grey['x0'],
                     'test': scores(yt, y_sim[0, :, 0], predicted, origins, n_t, n_h + 1),
                     'test_all_samples': rmse(y_sim[0, :, 0], yt)})
        sims[f'grey-box {n}'] = y_sim[0, :, 0]
        log(f'ARX and grey-box on 0..{n - 1}: test simulation RMSE '
            f'{rows[-2]["test"]["simulation_rmse"]:.4f}, '
            f'{rows[-1]["test"]["simulation_rmse"]:.4f} V')
    return rows, sims, fitted
