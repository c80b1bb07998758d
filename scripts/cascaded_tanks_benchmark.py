#!/usr/bin/env python3
"""The Cascaded Tanks benchmark measured on the real data: meta-learned NSSMs against the
supervised NSSM, an ARX model and the grey-box physics model, on the test record and on the
tank's twin in closed loop.

Per meta-training seed (--seed, several in turn): meta-trains iMAML and first-order MAML on
simulated systems of the `cascaded_tanks` family (--config: its learner set-up and
meta-training settings), then fits every model on the estimation record's first 300 samples
and on all 1024: the meta-models adapted with the learner's own eq. (infer), the supervised
NSSM from random weights, ARX, grey-box (these two do not depend on the seed). Every choice
(adaptation step size and steps, ARX orders) is made on the estimation record: fitted on its
head (samples 0..299, or 0..767 for the full record's choice), scored on samples 768..1023.
The test record is then predicted once: free-run simulation RMSE and T-step prediction RMSE,
volts. Beside them, the feature NARX of docs/nonlinear.md (iMAML through its closed-form
solve, on the same simulated systems) and the least-squares ARX(p) of its class: the head
adapted in closed form on every one-step equation of the fitted samples, the order p of
NARX_ORDERS chosen on the estimation record as the ARX orders are (simulation RMSE of
samples 768..1023), the test record simulated from its first p pairs. The twin (the family
at the grey-box fit to all 1024 samples) is tracked by the latent MPC of --config's
controller section on each fitted NSSM and by the true-model NMPC (docs/real_data.md says how
each model runs and where its initial state comes from).

Usage: python scripts/cascaded_tanks_benchmark.py --out runs/cts [--seed 0 1 2 3 4]
       [--config config/cascaded_tanks.yaml] [--figure docs/img/cascaded_tanks_test.png]
       [--twin-figure docs/img/cascaded_tanks_twin.png]
Writes OUT/seed_<s>/benchmark.json and narx.json per seed and OUT/summary.json, prints the
tables; every step is cached in OUT (run the same command again to resume). Exit status: 0
done, 2 bad arguments.
"""
import argparse
import dataclasses
import json
import math
import os
import sys
import time
from typing import Dict, List, Tuple

import numpy as np
import torch

from metampc_bringup.analysis.narx_records import free_run, predict
from metampc_bringup.analysis.retrack import summarise
from metampc_bringup.analysis.twin import nssm_weights, track_twin
from metampc_bringup.experiment_config import ConfigError, learner_config, load
from metampc_bringup.studies.nonlinear_regime import meta_models as narx_meta_models, \
    RegimeConfig
from metampc_bringup.studies.offline import request_meta_config
from metampc_learner.adapt import AdaptConfig
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
from metampc_learner.data import normalisation_from, simulate_source, SourceSet, Trajectory, \
    Windows
from metampc_learner.learner_params import AdaptJob, fit_settings
from metampc_learner.meta_train import meta_train
from metampc_learner.offline_adaptation import tstep_rmse
from metampc_learner.target_fit import ARX, fit_target, FitSettings, TargetFit
from metampc_model.feature_narx import FeatureNarx
from metampc_model.nssm import Nssm, Params
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.cascaded_tanks_data import load_cascaded_tanks
from metampc_plant.families.cascaded_tanks import GUESS
from metampc_plant.identification.arx import fit_arx, predict_arx, simulate_arx
from metampc_plant.identification.greybox import predict_greybox, simulate_family
from metampc_plant.identification.validation import arx_baseline, fit_greybox_head, Protocol, \
    rmse
from metampc_plant.registry import get_family

META = ('imaml', 'maml')       # the meta methods this benchmark compares (of META_METHODS)
FITS = (300, 1024)           # estimation samples 0..n-1 fitted
CHOOSE_HEAD = {300: 300, 1024: 768}   # head that the choices of each fit are made on
TAIL = 768                   # estimation samples TAIL..1023 score the choices
LRS = (0.03, 0.1, 0.3, 1.0)  # adaptation step sizes tried (the learner's Armijo maximum)
# Published free-run simulation RMSE on the test record, volts, models fitted on all 1024
# estimation samples (Math. Probl. Eng. 2021, 6613425, Table 2; docs/real_data.md).
PUBLISHED = {'BLA': 0.7574, 'PNLSS-I': 0.4498, 'NLSS2': 0.3433}
COLOURS = {'imaml': 'C0', 'maml': 'C1', 'supervised': 'C2'}   # the twin figure's


def log(text: str) -> None:
    print(f'[{time.strftime("%H:%M:%S")}] {text}', file=sys.stderr, flush=True)


def trajectory(u: np.ndarray, y: np.ndarray, start: int, stop: int) -> Trajectory:
    """Record samples start..stop-1 as a Trajectory: u[k] paired with the y[k+1] it acts on
    first (stop - start - 1 pairs)."""
    return Trajectory(np.arange(start, stop - 1), u[start:stop - 1], y[start + 1:stop])


def record_windows(model: Nssm, u: np.ndarray, y: np.ndarray, start: int, stop: int
                   ) -> Windows:
    """The NSSM's windows (H + T pairs) of record samples start..stop-1, normalised."""
    return Windows.from_trajectories([trajectory(u, y, start, stop)], model.norm, model.config,
                                     next(model.parameters()).dtype)


def simulate_nssm(model: Nssm, params: Params, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Free-run simulation over a record (N,): the encoder reads the H pairs (u[k], y[k+1]),
    k = 0..H-1, then the latent state runs on the inputs alone (eq. z_next) over one window of
    the whole record; y_hat[H+1..N-1], NaN at 0..H (not predicted)."""
    t = trajectory(u, y, 0, len(y))
    u_n, y_n = model.norm.normalise(t.u[None], t.y[None])
    dtype = next(model.parameters()).dtype
    with torch.no_grad():
        y_hat = torch.func.functional_call(model, params, (torch.as_tensor(u_n, dtype=dtype),
                                                           torch.as_tensor(y_n, dtype=dtype)))
    out = np.full(len(y), np.nan)
    out[model.config.history + 1:] = model.norm.denormalise_y(
        y_hat[0].double().numpy())[:, 0]
    return out


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


def meta_models(args, experiment, seed: int, folder: str
                ) -> Tuple[Nssm, Dict[str, Params], Dict[str, dict]]:
    """The meta-model of each method: folder/meta_<method>.pt when it holds this run's
    settings, else meta-trained on the family's simulated source set (and saved there)."""
    cfg = learner_config(experiment, seed)
    source_cfg = dataclasses.replace(cfg.source, seed=seed, **(
        {'n_systems': args.n_systems} if args.n_systems else {}))
    model, params, info = None, {}, {}
    source = None
    for method in META:
        meta = dataclasses.replace(cfg.meta, method=method, seed=seed,
                                   **request_meta_config(experiment, method))
        if args.meta_iterations:
            meta = dataclasses.replace(meta, iterations=args.meta_iterations)
        wanted = {'method': method, 'seed': seed, 'config': args.config,
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


def cached(path: str, wanted: dict):
    """The JSON object in `path` if it holds every item of `wanted`, else None."""
    if not os.path.exists(path):
        return None
    with open(path, encoding='utf-8') as f:
        found = json.load(f)
    return found if all(found.get(k) == v for k, v in wanted.items()) else None


def save(path: str, value: dict) -> None:
    with open(path, 'w', encoding='utf-8') as f:
        json.dump(value, f, indent=1)


class OutOfRange(ValueError):
    """A grey-box fit outside the family's parameter range (one line, exit 2)."""


def greybox(args, family, u: np.ndarray, y: np.ndarray, n: int, protocol: Protocol) -> dict:
    """The grey-box fit to estimation samples 0..n-1 (cached in OUT/greybox_<n>.json).

    Raises:
        OutOfRange: the fit left the family's parameter range (the twin of such a theta is not
            a member of the family): not cached, so a better budget fits again; a cached fit
            out of the range is fitted again too.
    """
    path = os.path.join(args.out, f'greybox_{n}.json')
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


def fit_all(args, seed: int, model, meta, family, data, protocol, settings: FitSettings
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
                                       trajectory(u, y, 0, head), held, args.max_steps,
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
        grey = greybox(args, family, u, y, n, protocol)
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


NARX_ORDERS = (2, 3, 4, 5)    # the feature NARX's orders p tried (the tanks are slow)
# The feature NARX's sizes (order replaced), meta-training (iMAML through the closed-form solve)
# and adaptation strength: docs/nonlinear.md's defaults, not tuned for this family.
NARX = RegimeConfig()


def narx_record(u: np.ndarray, y: np.ndarray, start: int, stop: int
                ) -> Tuple[np.ndarray, np.ndarray]:
    """Record samples start..stop-1 in the feature NARX's convention: (u (K, 1), y (K, 1)),
    u[k] produced y[k] (the pairs of `trajectory`)."""
    t = trajectory(u, y, start, stop)
    return t.u, t.y


def narx_metas(args, seed: int) -> Dict[int, FeatureNarx]:
    """The feature NARX of each order in NARX_ORDERS, meta-trained by iMAML on this seed's
    simulated source systems of the family (the NSSMs' source set)."""
    meta = dataclasses.replace(NARX.meta, seed=seed, **(
        {'iterations': args.meta_iterations} if args.meta_iterations else {}))
    overrides = {'learner': {'n_systems': args.n_systems}} if args.n_systems else {}
    return {p: narx_meta_models(dataclasses.replace(
        NARX, experiment=args.config, seeds=(seed,), order=p, meta=meta, overrides=overrides),
        log)['imaml'] for p in NARX_ORDERS}


def narx_simulation(model: FeatureNarx, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Free-run simulation over a whole record (N,): from the model's first p pairs (record
    samples 1..p), its own outputs after; NaN at sample 0 (not predicted)."""
    return np.concatenate([[np.nan], free_run(model, *narx_record(u, y, 0, len(y)))[:, 0]])


def narx_fit(method: str, meta: FeatureNarx, record: Trajectory, held: Trajectory,
             settings: FitSettings) -> Tuple[FeatureNarx, str]:
    """The feature NARX fitted on `record` by ``target_fit.fit_target`` ('imaml': the
    closed-form adaptation of docs/nonlinear.md, validated against the ARX; 'arx': the
    least-squares ARX(p) of its class), and its rule."""
    fitted = fit_target(method, meta, None, [record], [held], settings)
    return fitted.model, fitted.rule


def narx_rows(args, experiment, seed: int, data) -> List[dict]:
    """The feature NARX (iMAML, adapted with its closed-form head) and the ARX(p) of its class
    fitted on each of FITS and scored on the test record once, as the NSSMs are (the same
    samples scored, the same 10-step origins); OUT/seed_<s>/narx.json when it holds this
    run's settings, else computed. The order of each: the p of NARX_ORDERS whose fit to the
    choice head simulates the estimation record with the least RMSE on samples TAIL..1023."""
    path = os.path.join(args.out, f'seed_{seed}', 'narx.json')
    wanted = {'seed': seed, 'config': args.config, 'orders': list(NARX_ORDERS),
              'narx': repr(NARX), 'meta_iterations': args.meta_iterations,
              'n_systems': args.n_systems}
    found = cached(path, wanted)
    if found is not None:
        log(f'seed {seed}: feature NARX cached in {path}')
        return found['rows']
    os.makedirs(os.path.dirname(path), exist_ok=True)
    metas = narx_metas(args, seed)
    fits = {'feature NARX': 'imaml', 'ARX(p), NARX class': ARX}
    u, y, ut, yt = data.u_est, data.y_est, data.u_test, data.y_test
    learner = learner_config(experiment, seed)
    settings = dataclasses.replace(fit_settings(learner, AdaptJob('', 0, 1.0, 0.0, 0)),
                                   narx_gamma=NARX.meta.gamma, narx_horizon=NARX.meta.horizon)
    held = trajectory(u, y, TAIL, len(y))
    n_h, n_t = learner.nssm.history, learner.nssm.loss_horizon
    origins = np.arange(n_h, len(yt) - n_t)
    rows = []
    for n in FITS:
        for name, method in fits.items():
            validation = {}
            for p, meta in metas.items():
                fit = narx_fit(method, meta, trajectory(u, y, 0, CHOOSE_HEAD[n]), held, settings)
                validation[p] = rmse(narx_simulation(fit[0], u, y)[TAIL:], y[TAIL:])
            p = min(validation, key=lambda q: (not math.isfinite(validation[q]), validation[q]))
            model, rule = narx_fit(method, metas[p], trajectory(u, y, 0, n), held, settings)
            predicted = predict(model, *narx_record(ut, yt, 0, len(yt)), origins - 1, n_t)
            rows.append({'fit': n, 'model': name, 'rule': rule,
                         'choice': {'order': p, 'validation_sim_rmse': {
                             str(q): v for q, v in validation.items()}},
                         'test': scores(yt, narx_simulation(model, ut, yt), predicted[..., 0],
                                        origins, n_t, n_h + 1)})
            log(f'{name} on 0..{n - 1}: order {p} ({rule}); test simulation RMSE '
                f'{rows[-1]["test"]["simulation_rmse"]:.4f} V')
    save(path, {**wanted, 'rows': rows})
    return rows


def series(episode) -> Dict[str, np.ndarray]:
    """A tracking run's level y (K + 1,), pump voltage u (K + 1,) and reference (K,), V."""
    return {'y': episode.y[:, 0], 'u': episode.u[:, 0], 'y_ref': episode.y_ref[:, 0]}


def twin_nmpc(args, experiment, grey: dict) -> Tuple[dict, Dict[str, np.ndarray]]:
    """The true-model NMPC's run on the twin, the same for every seed (OUT/twin_nmpc.json when
    it holds this twin and experiment, else flown and saved there): its result and series."""
    path = os.path.join(args.out, 'twin_nmpc.json')
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


def run_seed(args, experiment, seed: int, data, protocol: Protocol, grey: dict, nmpc: dict
             ) -> dict:
    """One seed's meta-training, fits, test-record figures and twin runs: OUT/seed_<s>/
    benchmark.json (and the series in series.npz there) when it holds this run's settings,
    else computed (meta-models cached there too)."""
    folder = os.path.join(args.out, f'seed_{seed}')
    path = os.path.join(folder, 'benchmark.json')
    wanted = {'seed': seed, 'config': args.config, 'max_steps': args.max_steps,
              'meta_iterations': args.meta_iterations, 'n_systems': args.n_systems,
              'greybox': grey, 'nmpc': nmpc,
              'experiment': json.dumps(experiment.to_dict(), sort_keys=True)}
    found = cached(path, wanted)
    if found is not None and os.path.exists(os.path.join(folder, 'series.npz')):
        log(f'seed {seed}: cached in {path}')
        return found
    os.makedirs(folder, exist_ok=True)
    torch.manual_seed(seed)
    start = time.monotonic()
    model, meta, meta_info = meta_models(args, experiment, seed, folder)
    settings = fit_settings(learner_config(experiment, seed), AdaptJob('', 0, 1.0, 0.0, 0))
    rows, sims, fitted = fit_all(args, seed, model, meta, get_family('cascaded_tanks'), data,
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


def summary(reports: List[dict], nmpc: dict) -> dict:
    """Over the seeds: each model's test figures per fit (values by seed, median, min, max)
    and the twin's tracking (retrack.summarise: cost / NMPC by seed, median, worst, escapes)."""
    test: Dict[str, dict] = {}
    for report in reports:
        for r in report['rows']:
            key = f'{r["fit"]} {r["model"]}'
            row = test.setdefault(key, {'fit': r['fit'], 'model': r['model']})
            for name, value in r['test'].items():
                row.setdefault(name, []).append(value)
    for row in test.values():
        for key in ('simulation_rmse', 'prediction_rmse'):
            values = row[key]
            row[key] = {'values': values, 'median': float(np.median(values)),
                        'min': min(values), 'max': max(values)}
    return {'seeds': [r['seed'] for r in reports], 'test': list(test.values()),
            'twin': summarise({r['seed']: r['twin'] for r in reports}), 'nmpc': nmpc,
            'published': PUBLISHED}


def spread(figure: dict) -> str:
    """median (min..max) of a test figure over the seeds, volts (the value for one seed)."""
    if figure['min'] == figure['max']:
        return f'{figure["median"]:.4f}'
    return f'{figure["median"]:.4f} ({figure["min"]:.4f}..{figure["max"]:.4f})'


def table(result: dict) -> str:
    """The markdown table of the test figures (volts), median (min..max) over the seeds."""
    lines = ['| fitted on | model | simulation RMSE (V) | 10-step prediction RMSE (V) |',
             '|---|---|---|---|']
    for r in result['test']:
        lines.append(f"| estimation 0..{r['fit'] - 1} | {r['model']} | "
                     f"{spread(r['simulation_rmse'])} | {spread(r['prediction_rmse'])} |")
    for name, value in PUBLISHED.items():
        lines.append(f'| estimation 0..1023 (published) | {name} | {value:.4f} | |')
    return '\n'.join(lines)


def twin_table(result: dict) -> str:
    """The markdown table of the twin's tracking cost / the NMPC's (inf: escaped)."""
    seeds = result['seeds']
    lines = [f'| fitted on | model | cost / NMPC, seeds {", ".join(map(str, seeds))} | median | '
             'worst | escapes | refused | mean steady offset (V) |', '|---' * 8 + '|']
    for variant, methods in result['twin'].items():
        for method, row in methods.items():
            ratios = ', '.join(f'{row["ratios"][s]:.3g}' for s in seeds)
            lines.append(f'| estimation 0..{int(variant.split()[1]) - 1} | {method} | {ratios} | '
                         f'{row["median"]:.3g} | {row["worst"]:.3g} | {row["escapes"]} | '
                         f'{row["rejected"]} | {row["mean_offset"]:.3f} |')
    nmpc = result['nmpc']
    lines.append(f'| | NMPC (true model) | cost {nmpc["cost"]:.4g} | | | '
                 f'{int(nmpc["escaped"])} | | {np.mean(nmpc["offsets"]):.3f} |')
    return '\n'.join(lines)


def figure(path: str, yt: np.ndarray, sims: Dict[str, np.ndarray], ts: float) -> None:
    """The test record's measured level and each model's free-run simulation, per fit."""
    plt = _pyplot()
    fig, axes = plt.subplots(len(FITS), 1, figsize=(8, 5.5), sharex=True)
    t = np.arange(len(yt)) * ts
    for ax, n in zip(axes, FITS):
        ax.plot(t, yt, 'k', lw=1.5, label='measured')
        for name in (*META, 'supervised', 'ARX', 'grey-box'):
            ax.plot(t, sims[f'test {name} {n}'], lw=0.9, label=name)
        ax.set_ylabel('level (V)')
        ax.set_title(f'test record, free run; fitted on estimation samples 0..{n - 1}',
                     fontsize=9)
        ax.set_ylim(0, 12)
    axes[0].legend(fontsize=7, ncol=6, loc='upper left')
    axes[-1].set_xlabel('time (s)')
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def twin_figure(path: str, seed: int, runs: Dict[str, np.ndarray],
                nmpc: Dict[str, np.ndarray], ts: float) -> None:
    """One seed's tracking runs on the twin, per fit: the level against the reference, and
    the pump voltage."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, len(FITS), figsize=(9, 5), sharex=True,
                             gridspec_kw={'height_ratios': [2, 1]})
    t = np.arange(len(nmpc['y'])) * ts
    for col, n in enumerate(FITS):
        top, bottom = axes[0, col], axes[1, col]
        for name in ('supervised', *META, 'nmpc'):     # the NMPC on top
            run = nmpc if name == 'nmpc' else {
                part: runs[f'twin {name} {n} {part}'] for part in ('y', 'u')}
            style = {'color': 'k', 'lw': 1.0, 'label': 'NMPC'} if name == 'nmpc' else {
                'color': COLOURS[name], 'lw': 0.8, 'label': name,
                'alpha': 0.6 if name == 'supervised' else 1.0}
            top.plot(t, run['y'], **style)
            bottom.plot(t, run['u'], **style)
        top.plot(t[1:], nmpc['y_ref'], 'r--', lw=0.8, label='reference')
        top.set_title(f'twin, seed {seed}; NSSMs fitted on estimation 0..{n - 1}', fontsize=9)
        top.set_ylim(0, 11)
        bottom.set_xlabel('time (s)')
    axes[0, 0].set_ylabel('lower level (V)')
    axes[1, 0].set_ylabel('pump (V)')
    axes[0, 0].legend(fontsize=7, ncol=2, loc='lower left')
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', required=True, help='folder of the results and the cache')
    parser.add_argument('--seed', type=int, nargs='+', default=[0],
                        help='meta-training seeds, run in turn (each: source set, '
                             'meta-training and supervised initial weights; OUT/seed_<s>/)')
    parser.add_argument('--config', default='config/cascaded_tanks.yaml',
                        help='the family\'s experiment configuration (learner, meta_train, '
                             'controller, reference)')
    parser.add_argument('--figure', default='', help='PNG of the test-record free runs '
                        '(the first seed)')
    parser.add_argument('--twin-figure', default='', help='PNG of the tracking runs on the '
                        'twin (the first seed)')
    parser.add_argument('--max-steps', type=int, default=200,
                        help='adaptation steps searched (0..this) on the estimation record')
    parser.add_argument('--meta-iterations', type=int, default=0,
                        help='outer steps of every meta-training (0: the config\'s for '
                             'the NSSMs, 1000 for the feature NARX)')
    parser.add_argument('--n-systems', type=int, default=0,
                        help='source systems (0: the config\'s)')
    parser.add_argument('--candidates', type=int, default=512, help='grey-box candidates')
    parser.add_argument('--polish', type=int, default=4, help='grey-box searches')
    parser.add_argument('--substeps', type=int, default=4, help='grey-box RK4 steps a sample')
    args = parser.parse_args(argv)
    try:
        experiment = load(args.config)
        if experiment.plant_family.name != 'cascaded_tanks':
            raise ConfigError(f'--config {args.config}: family {experiment.plant_family.name}, '
                              'not cascaded_tanks')
        if min(*args.seed, args.max_steps, args.meta_iterations, args.n_systems) < 0:
            raise ConfigError('--seed, --max-steps, --meta-iterations, --n-systems must be >= 0')
        if len(set(args.seed)) != len(args.seed):
            raise ConfigError(f'--seed: each seed once, got {args.seed}')
        if os.path.exists(args.out) and not os.path.isdir(args.out):
            raise ConfigError(f'--out {args.out} exists and is not a folder')
        # The grey-box search's candidates are drawn with rng(0) whatever the seed: ARX and
        # grey-box do not depend on it.
        protocol = Protocol(fit_samples=300, validation_start=TAIL, candidates=args.candidates,
                            polish=args.polish, substeps=args.substeps, seed=0)
        protocol.check(1024)
    except ValueError as err:       # ConfigError is one
        print(f'cascaded_tanks_benchmark: {err}', file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    torch.set_num_threads(1)
    data = load_cascaded_tanks()
    # The twin: the family at the grey-box fit to the whole estimation record.
    try:
        grey = greybox(args, get_family('cascaded_tanks'), data.u_est, data.y_est, FITS[-1],
                       protocol)
        nmpc, nmpc_series = twin_nmpc(args, experiment, grey)
        reports = [run_seed(args, experiment, seed, data, protocol, grey, nmpc)
                   for seed in args.seed]
    except OutOfRange as err:
        print(f'cascaded_tanks_benchmark: {err}', file=sys.stderr)
        return 2
    for report in reports:
        report['rows'] = report['rows'] + narx_rows(args, experiment, report['seed'], data)
    result = summary(reports, nmpc)
    save(os.path.join(args.out, 'summary.json'), result)
    if args.figure or args.twin_figure:
        first = np.load(os.path.join(args.out, f'seed_{args.seed[0]}', 'series.npz'))
        if args.figure:
            figure(args.figure, data.y_test, first, data.ts)
        if args.twin_figure:
            twin_figure(args.twin_figure, args.seed[0], first, nmpc_series, data.ts)
    print(table(result))
    print()
    print(twin_table(result))
    return 0


if __name__ == '__main__':
    sys.exit(main())
