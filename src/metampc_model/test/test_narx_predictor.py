"""The numpy feature NARX of the controller (narx_predictor) against the torch model."""
import numpy as np
import pytest
import torch

from metampc_model.feature_narx import init_params, rollout
from metampc_model.narx_predictor import NarxPredictor
from metampc_model.narx_shape import NarxShape
from metampc_model.normalisation import Normalisation


def test_the_prediction_is_the_torch_rollout_in_physical_units():
    """T steps fed back into the lags, numpy, against feature_narx.rollout (torch, normalised
    units) of the same weights: fails on a wrong lag shift or a wrong unit conversion."""
    shape = NarxShape(n_u=1, n_y=2, order=3, features=4, hidden=(5,))
    params = init_params(shape, 3)
    params['head'] = torch.randn(params['head'].shape, generator=torch.Generator().manual_seed(4),
                                 dtype=torch.float64) * 0.3
    norm = Normalisation(np.array([0.2]), np.array([1.5]), np.array([0.1, -0.3]),
                         np.array([2.0, 0.5]))
    rng = np.random.default_rng(0)
    u_hist, y_hist = rng.normal(size=(3, 1)), rng.normal(size=(3, 2))
    u_future = rng.normal(size=(6, 1))
    pred = NarxPredictor(shape, norm, {k: v.numpy() for k, v in params.items()})
    got = pred.predict(pred.encode(u_hist, y_hist), u_future)
    u_n, y_n = norm.normalise(u_hist, y_hist)
    s_n = np.concatenate([y_n[::-1].reshape(-1), u_n[::-1][:2].reshape(-1)])
    want = rollout(shape, params, torch.from_numpy(s_n),
                   torch.from_numpy((u_future - norm.u_mean) / norm.u_std)).numpy()
    np.testing.assert_allclose(got, want * norm.y_std + norm.y_mean, atol=1e-10)


def test_the_regressors_are_the_torch_model_s_in_normalised_units():
    """phi(s_t, u_{t+1}) of physical inputs against feature_narx.regressors of the normalised
    ones (fails where the features read physical s, or the constant is left out)."""
    from metampc_model.feature_narx import regressors
    shape = NarxShape(n_u=1, n_y=2, order=2, features=3, hidden=(4,))
    params = init_params(shape, 5)
    norm = Normalisation(np.array([0.2]), np.array([1.5]), np.array([0.1, -0.3]),
                         np.array([2.0, 0.5]))
    pred = NarxPredictor(shape, norm, params)
    rng = np.random.default_rng(1)
    s, u = rng.normal(size=shape.n_s), rng.normal(size=1)
    s_n = (s - np.concatenate([norm.y_mean, norm.y_mean, norm.u_mean])) / np.concatenate(
        [norm.y_std, norm.y_std, norm.u_std])
    want = regressors(shape, params, torch.from_numpy(s_n),
                      torch.from_numpy((u - norm.u_mean) / norm.u_std)).numpy()
    np.testing.assert_allclose(pred.regressors(s, u), want, atol=1e-12)
    assert pred.regressors(s, u)[-1] == 1.0


def test_a_head_in_place_of_the_models():
    """The one-step prediction is the head times the regressors; a head given to linearise()
    or set by set_head() is the one used; a head of another shape is refused."""
    shape = NarxShape(n_u=1, n_y=2, order=2, features=3, hidden=(4,))
    params = {k: v.numpy() for k, v in init_params(shape, 5).items()}
    rng = np.random.default_rng(1)
    head, other = rng.normal(size=(2, shape.n_phi)), rng.normal(size=(2, shape.n_phi))
    norm = Normalisation(np.array([0.2]), np.array([1.5]), np.array([0.1, -0.3]),
                         np.array([2.0, 0.5]))
    pred = NarxPredictor(shape, norm, {**params, 'head': head})
    s, u = rng.normal(size=shape.n_s), rng.normal(size=1)
    np.testing.assert_allclose(pred.step(s, u),
                               head @ pred.regressors(s, u) * norm.y_std + norm.y_mean,
                               atol=1e-12)
    given = pred.linearise(s, u, other)
    assert np.array_equal(pred.head, head)
    pred.set_head(other)
    assert np.array_equal(pred.head, other)
    np.testing.assert_allclose(pred.step(s, u),
                               other @ pred.regressors(s, u) * norm.y_std + norm.y_mean,
                               atol=1e-12)
    np.testing.assert_array_equal(pred.linearise(s, u).A, given.A)
    with pytest.raises(ValueError):
        pred.set_head(other[:, 1:])
