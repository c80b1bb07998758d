"""PredictionError against the torch NSSM: the one-step and T-step errors at y_k are l_SSM's
terms of the windows that end at k (eq. loss, normalised units), computed by functional_call."""
import dataclasses
import math

import numpy as np
import pytest
import torch
from torch.func import functional_call

from metampc_controller.adaptation_trigger import TriggerConfig
from metampc_controller.controller_core import build_model, ControllerCore, ModelBundle
from metampc_controller.controller_params import ControllerConfig
from metampc_model.manual_model import linearised_vdp_nssm
from metampc_controller.mpc import MpcConfig
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_controller.prediction_error import PredictionError
from metampc_model.predictor import NssmPredictor
from metampc_model.weights_codec import DecodedWeights
from metampc_plant.simulator import Plant, PlantConfig


def torch_error(model, params, norm, u, y, end, t):
    """mean_i (y_n[end] - yhat_n)^2 of the window whose T = t predictions end at `end`."""
    h = model.config.history
    rows = slice(end - t - h + 1, end + 1)
    u_n, y_n = norm.normalise(u[rows][None], y[rows][None])
    cfg = NssmConfig(**{**model.config.__dict__, 'loss_horizon': t})
    with torch.no_grad():
        y_hat = functional_call(Nssm(cfg, norm, seed=0, dtype=torch.float64), params,
                                (torch.as_tensor(u_n), torch.as_tensor(y_n)))
    return float(np.mean((y_n[0, -1] - y_hat[0, -1].numpy()) ** 2))


def test_errors_are_the_loss_terms_of_the_torch_model():
    config = NssmConfig(history=4, loss_horizon=6, hidden=(16,), n_z=3)
    norm = Normalisation(u_mean=np.array([0.1]), u_std=np.array([0.7]),
                         y_mean=np.array([0.2, -0.1]), y_std=np.array([1.5, 0.8]))
    model = Nssm(config, norm, seed=3, dtype=torch.float64)
    params = model.params()
    predictor = NssmPredictor(config, norm, params)
    monitor = PredictionError(predictor.latent, norm.y_std, config.loss_horizon)
    rng = np.random.default_rng(1)
    n, h, t = 40, config.history, config.loss_horizon
    u, y = rng.uniform(-1, 1, (n, 1)), rng.normal(0, 1, (n, 2))
    for k in range(h - 1, n):
        z = predictor.encode(u[k - h + 1:k + 1], y[k - h + 1:k + 1])
        one, t_step, change = monitor.update(k, u[k], y[k], z)
        age = k - (h - 1)       # rollouts that exist: started at steps h-1 .. k-1
        assert math.isnan(one) == (age < 1) and math.isnan(t_step) == (age < t), k
        if age >= 1:
            assert one == pytest.approx(torch_error(model, params, norm, u, y, k, 1), rel=1e-9)
        if age >= t:
            assert t_step == pytest.approx(torch_error(model, params, norm, u, y, k, t),
                                           rel=1e-9)
            assert change == pytest.approx(np.mean(((y[k] - y[k - t]) / norm.y_std) ** 2))
        else:
            assert math.isnan(change)
    # A gap in the steps (samples missed, a reset) restarts the rollouts.
    z = predictor.encode(u[-h:], y[-h:])
    assert all(map(math.isnan, monitor.update(n + 5, u[-1], y[-1], z)))


def test_the_tick_reports_the_errors_of_the_model_in_use():
    """The hand-built linearised model on the plant it was linearised for: small errors once
    the rollouts exist, NaN before (and after a reset), far larger against another theta."""
    bundle = build_model(DecodedWeights(*linearised_vdp_nssm(0.5, 0.1, 10)), 1, 'manual',
                         'adapted', MpcConfig(time_limit=30.0), 1, 2)
    horizon = bundle.predictor.config.loss_horizon

    def errors(theta_plant):
        core = ControllerCore(ControllerConfig())
        core.offer(dataclasses.replace(bundle, prediction=PredictionError(
            bundle.predictor.latent, bundle.predictor.norm.y_std, horizon)))
        plant = Plant(PlantConfig(theta=(theta_plant,), x0=(0.3, 0.0)))
        y, u, out = plant.output(), 0.0, []
        for k in range(60):
            core.observe(k, [u], y)
            res = core.tick()
            out.append(res.prediction_errors)
            u = float(res.u[0])
            y = plant.step([u])
        return np.array(out)

    same, other = errors(0.5), errors(-1.5)
    assert np.isnan(same[0]).all() and np.isnan(same[:horizon, 1]).all()
    assert np.isfinite(same[1:, 0]).all() and np.isfinite(same[horizon:, 1]).all()
    assert np.nanmean(other[:, 1]) > 10 * np.nanmean(same[:, 1])


def test_a_model_without_monitor_measures_nothing_asks_nothing_and_controls_alike():
    """ModelBundle.of(monitor=False) (online collection's): the ticks report no errors and
    make no adaptation request even under a periodic trigger, and answer with the same inputs
    bit for bit as the monitored model (monitoring never changes control)."""
    decoded = DecodedWeights(*linearised_vdp_nssm(0.5, 0.1, 10))
    mpc = MpcConfig(time_limit=30.0)
    periodic = TriggerConfig(adaptation='periodic', adapt_period=1.0)
    config = ControllerConfig(mpc=mpc, trigger=periodic)
    runs = []
    for bundle in (build_model(decoded, 1, 'manual', 'adapted', mpc, 1, 2),
                   ModelBundle.of(NssmPredictor(decoded.config, decoded.norm, decoded.params),
                                  1, 'manual', 'adapted', mpc, monitor=False)):
        core = ControllerCore(config)
        core.offer(bundle)
        plant = Plant(PlantConfig(theta=(0.5,), x0=(0.3, 0.0)))
        y, u, ticks = plant.output(), 0.0, []
        for k in range(40):
            core.observe(k, [u], y)
            ticks.append(core.tick())
            u = float(ticks[-1].u[0])
            y = plant.step([u])
        runs.append(ticks)
    monitored, unmonitored = runs
    assert np.isfinite(monitored[-1].prediction_errors).all()
    assert any(t.request is not None for t in monitored)
    assert all(np.isnan(t.prediction_errors).all() and t.request is None for t in unmonitored)
    assert [t.u.tolist() for t in monitored] == [t.u.tolist() for t in unmonitored]
