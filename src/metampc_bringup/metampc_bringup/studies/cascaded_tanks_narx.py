"""The Cascaded Tanks benchmark's feature NARX: fitted and scored as the NSSMs are.

The feature NARX of docs/nonlinear.md (iMAML through its closed-form solve, on the NSSMs'
simulated source systems, each order of NARX_ORDERS) and the least-squares ARX(p) of its class
(``target_fit.fit_target``), fitted on each of the benchmark's FITS, the order chosen on the
estimation record (simulation RMSE of samples TAIL..1023), scored on the test record once
(free-run simulation and 10-step prediction RMSE, volts). Cached per seed (narx.json). The
record in the NARX's convention: u[k] produced y[k] (:func:`narx_record`). No ROS.
"""
import dataclasses
import math
import os
from typing import Dict, List, Tuple

import numpy as np

from metampc_bringup.analysis.narx_records import free_run, predict
from metampc_bringup.analysis.nssm_records import trajectory
from metampc_bringup.experiment_config import learner_config
from metampc_bringup.studies.cascaded_tanks import CHOOSE_HEAD, FITS, log, scores, TAIL, \
    TanksOptions
from metampc_bringup.studies.json_cache import cached, save
from metampc_bringup.studies.nonlinear_regime import meta_models as narx_meta_models, \
    RegimeConfig
from metampc_learner.data import Trajectory
from metampc_learner.learner_params import AdaptJob, fit_settings
from metampc_learner.target_fit import ARX, fit_target, FitSettings
from metampc_model.feature_narx import FeatureNarx
from metampc_plant.identification.validation import rmse

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


def narx_metas(options: TanksOptions, seed: int) -> Dict[int, FeatureNarx]:
    """The feature NARX of each order in NARX_ORDERS, meta-trained by iMAML on this seed's
    simulated source systems of the family (the NSSMs' source set)."""
    meta = dataclasses.replace(NARX.meta, seed=seed, **(
        {'iterations': options.meta_iterations} if options.meta_iterations else {}))
    overrides = {'learner': {'n_systems': options.n_systems}} if options.n_systems else {}
    return {p: narx_meta_models(dataclasses.replace(
        NARX, experiment=options.config, seeds=(seed,), order=p, meta=meta, overrides=overrides),
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


def narx_rows(options: TanksOptions, experiment, seed: int, data) -> List[dict]:
    """The feature NARX (iMAML, adapted with its closed-form head) and the ARX(p) of its class
    fitted on each of FITS and scored on the test record once, as the NSSMs are (the same
    samples scored, the same 10-step origins); OUT/seed_<s>/narx.json when it holds this
    run's settings, else computed. The order of each: the p of NARX_ORDERS whose fit to the
    choice head simulates the estimation record with the least RMSE on samples TAIL..1023."""
    path = os.path.join(options.out, f'seed_{seed}', 'narx.json')
    wanted = {'seed': seed, 'config': options.config, 'orders': list(NARX_ORDERS),
              'narx': repr(NARX), 'meta_iterations': options.meta_iterations,
              'n_systems': options.n_systems}
    found = cached(path, wanted)
    if found is not None:
        log(f'seed {seed}: feature NARX cached in {path}')
        return found['rows']
    os.makedirs(os.path.dirname(path), exist_ok=True)
    metas = narx_metas(options, seed)
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
