"""The NSSM: shapes, seeding, flat round trip, latent model and numpy encoder (no ROS)."""

import numpy as np
import pytest
import torch
from torch.func import functional_call

from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params, Nssm, prediction_loss, torch_params
from metampc_model.nssm_config import NssmConfig, param_shapes
from metampc_model.predictor import latent_model, NssmPredictor
from metampc_model.weights_codec import FlatWeights

torch.set_num_threads(1)


def _norm():
    return Normalisation(u_mean=[0.1], u_std=[0.6], y_mean=[0.05, -0.2], y_std=[2.9, 3.1])


def _windows(config, n, seed, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    return (torch.randn(n, config.window, config.n_u, generator=gen, dtype=dtype),
            torch.randn(n, config.window, config.n_y, generator=gen, dtype=dtype))


def test_functional_call_shapes_and_loss_definition():
    config = NssmConfig()
    model = Nssm(config)
    params = model.params()
    assert list(params) == list(param_shapes(config))
    assert {k: tuple(v.shape) for k, v in params.items()} == dict(param_shapes(config))
    u, y = _windows(config, 7, 0)
    y_hat = functional_call(model, params, (u, y))
    assert y_hat.shape == (7, config.loss_horizon, config.n_y)
    expected = ((y_hat - y[:, config.history:]) ** 2).sum(-1).mean()
    assert torch.allclose(prediction_loss(model, params, u, y), expected)


def test_closed_form_rollout_equals_recursion():
    config = NssmConfig(loss_horizon=23)
    model = Nssm(config, seed=3, dtype=torch.float64)
    p = model.params()
    gen = torch.Generator().manual_seed(1)
    z0 = torch.randn(4, config.n_z, generator=gen, dtype=torch.float64)
    u = torch.randn(4, config.loss_horizon, config.n_u, generator=gen, dtype=torch.float64)
    z = z0
    outputs = []
    for k in range(config.loss_horizon):
        z = z @ p['A'].T + u[:, k] @ p['B'].T
        outputs.append(z @ p['C'].T)
    with torch.no_grad():
        y_hat = model.rollout(z0, u)
    assert torch.allclose(y_hat, torch.stack(outputs, 1), atol=1e-12)


def test_init_is_seeded_and_leaves_global_rng_alone():
    config = NssmConfig()
    state = torch.random.get_rng_state()
    a, b, c = init_params(config, 5), init_params(config, 5), init_params(config, 6)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a['encoder.0.weight'], c['encoder.0.weight'])
    model = Nssm(config, seed=5)
    assert all(torch.equal(model.params()[k], a[k]) for k in a)


def test_flat_weights_round_trip_is_exact():
    config = NssmConfig(hidden=(32, 16), n_z=4, history=6)
    params = init_params(config, 11)
    flat = FlatWeights.from_params(params)
    assert flat.params.dtype == np.float32
    assert flat.params.size == sum(v.numel() for v in params.values())
    assert len(flat.shape_offsets) == len(flat.names) + 1
    for i, name in enumerate(flat.names):
        assert flat.shape_of(i) == tuple(params[name].shape)
    back = flat.to_params(config)
    assert list(back) == list(params)
    assert all(back[k].dtype == np.float32 for k in back)
    assert all(np.array_equal(back[k], params[k].numpy()) for k in params)
    # what a message carries: plain lists and a float32 array
    again = FlatWeights(list(flat.names), list(flat.shape_offsets), list(flat.shapes),
                        np.array(flat.params.tolist(), dtype=np.float32))
    assert all(np.array_equal(again.to_params(config)[k], params[k].numpy()) for k in params)


def test_flat_weights_rejects_mismatch():
    config = NssmConfig(hidden=(8,), n_z=3, history=2)
    flat = FlatWeights.from_params(init_params(config, 0))
    with pytest.raises(ValueError, match='do not fit'):
        flat.to_params(NssmConfig(hidden=(9,), n_z=3, history=2))
    bad = FlatWeights(flat.names, flat.shape_offsets, flat.shapes, flat.params.copy())
    bad.params[3] = np.nan
    with pytest.raises(ValueError, match='non-finite'):
        bad.to_params(config)
    with pytest.raises(ValueError, match='parameters'):
        FlatWeights(flat.names, flat.shape_offsets, flat.shapes, flat.params[:-1]).to_params(
            config)


@pytest.mark.parametrize('dtype, tol', [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_latent_model_reproduces_the_rollout_in_physical_units(dtype, tol):
    config = NssmConfig()
    norm = _norm()
    model = Nssm(config, norm, seed=4, dtype=dtype)
    params = model.params()
    rng = np.random.default_rng(0)
    u_phys = rng.uniform(-1, 1, size=(5, config.window, 1))
    y_phys = rng.normal(0, 2, size=(5, config.window, 2))
    u_n, y_n = norm.normalise(u_phys, y_phys)
    with torch.no_grad():
        y_hat_n = functional_call(model, params, (torch.as_tensor(u_n, dtype=dtype),
                                                  torch.as_tensor(y_n, dtype=dtype)))
    y_hat = norm.denormalise_y(y_hat_n.double().numpy())
    predictor = NssmPredictor(config, norm, params)
    lm = latent_model(params, norm)
    lm.validate()
    n_h = config.history
    for i in range(5):
        got = predictor.predict(u_phys[i, :n_h], y_phys[i, :n_h], u_phys[i, n_h:])
        scale = max(1.0, np.abs(y_hat[i]).max())
        assert np.abs(got - y_hat[i]).max() <= tol * scale
        # the same through LatentModel.step / output, as the MPC uses it
        z = predictor.encode(u_phys[i, :n_h], y_phys[i, :n_h])
        for k in range(config.loss_horizon):
            z = lm.step(z, u_phys[i, n_h + k])
            assert np.abs(lm.output(z) - y_hat[i, k]).max() <= tol * scale
    with torch.no_grad():
        z_torch = model.encode(torch.as_tensor(u_n[:1, :n_h], dtype=dtype),
                               torch.as_tensor(y_n[:1, :n_h], dtype=dtype))[0]
    assert np.allclose(predictor.encode(u_phys[0, :n_h], y_phys[0, :n_h]),
                       z_torch.double().numpy(), atol=tol, rtol=tol)


def test_latent_model_formula():
    config = NssmConfig(n_u=1, n_y=2)
    norm = _norm()
    params = init_params(config, 9, torch.float64)
    lm = latent_model(params, norm)
    a, b, c = (params[k].numpy() for k in 'ABC')
    assert np.allclose(lm.A, a)
    assert np.allclose(lm.B, b / 0.6)
    assert np.allclose(lm.e, -b[:, 0] * (0.1 / 0.6))
    assert np.allclose(lm.C, np.diag([2.9, 3.1]) @ c)
    assert np.allclose(lm.d, [0.05, -0.2])


def test_validation():
    with pytest.raises(ValueError, match='n_z'):
        NssmConfig(n_z=0).validate()
    with pytest.raises(ValueError, match='scales'):
        Nssm(NssmConfig(), Normalisation([0.0], [0.0], [0, 0], [1, 1]))
    with pytest.raises(ValueError, match='y_mean'):
        Nssm(NssmConfig(), Normalisation([0.0], [1.0], [0.0], [1, 1]))


def test_decoded_arrays_give_the_same_model_as_the_tensors():
    """Decoding gives float32 arrays (no torch); torch_params turns them back into the very
    tensors that were encoded, in new memory, and the numpy predictor built from either (or from
    tensors that carry a gradient) is the same, bit for bit."""
    config = NssmConfig(hidden=(16,), n_z=3, history=4)
    params = init_params(config, 3)
    arrays = FlatWeights.from_params(params).to_params(config)
    back = torch_params(arrays)
    assert list(back) == list(params)
    assert all(back[k].dtype == torch.float32 and torch.equal(back[k], params[k])
               for k in params)
    back['A'][0, 0] = 7.0
    assert arrays['A'][0, 0] != 7.0
    rng = np.random.default_rng(1)
    u, y, u_future = rng.normal(size=(4, 1)), rng.normal(size=(4, 2)), rng.normal(size=(6, 1))
    grad = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    want = NssmPredictor(config, _norm(), arrays).predict(u, y, u_future)
    for same in (params, grad):
        assert np.array_equal(NssmPredictor(config, _norm(), same).predict(u, y, u_future), want)
