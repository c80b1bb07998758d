"""NssmPredictor.encode, the numpy encoder of eq. (z) on the controller's tick, against the
torch NSSM's forward pass (float64) and against the plain formula ``w @ h + b`` layer by
layer, bit for bit."""
import numpy as np
import pytest
import torch

from metampc_model.normalisation import Normalisation
from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_model.predictor import NssmPredictor

torch.set_num_threads(1)


@pytest.mark.parametrize('n_u,n_y,hidden,history', [
    (1, 2, (128, 128), 10),      # the default NSSM, as the controller runs it
    (2, 3, (64, 32, 16), 7),
    (1, 1, (8,), 1)])
def test_encoder_is_the_torch_forward_and_the_plain_formula(n_u, n_y, hidden, history):
    config = NssmConfig(n_u=n_u, n_y=n_y, hidden=hidden, history=history, n_z=4)
    rng = np.random.default_rng(history)
    norm = Normalisation(rng.normal(size=n_u), rng.uniform(0.3, 3.0, n_u),
                         rng.normal(size=n_y), rng.uniform(0.3, 3.0, n_y))
    model = Nssm(config, norm, seed=history, dtype=torch.float64)
    params = model.params()
    predictor = NssmPredictor(config, norm, params)
    layers = [(params[f'encoder.{i}.weight'].numpy(), params[f'encoder.{i}.bias'].numpy())
              for i in range(len(hidden) + 1)]
    for _ in range(50):
        u = rng.uniform(-2.0, 2.0, size=(history, n_u))
        y = rng.normal(0.0, 3.0, size=(history, n_y))
        z = predictor.encode(u, y)
        assert z.shape == (config.n_z,) and z.dtype == np.float64
        # The torch NSSM's encoder on the normalised history (eq. z).
        u_n, y_n = norm.normalise(u, y)
        with torch.no_grad():
            z_torch = model.encode(torch.as_tensor(u_n[None]), torch.as_tensor(y_n[None]))[0]
        assert np.abs(z - z_torch.numpy()).max() <= 1e-10 * max(1.0, np.abs(z).max())
        # The plain formula, written out: the same float64 operations, so the same bits.
        h = np.concatenate([u_n, y_n], axis=1).reshape(-1)
        for i, (w, b) in enumerate(layers):
            h = w @ h + b
            if i < len(layers) - 1:
                h = np.maximum(h, 0.0)
        np.testing.assert_array_equal(z, h)
        # Flat or float32 histories are read as before (reshaped, converted to float64).
        np.testing.assert_array_equal(predictor.encode(u.ravel(), y), z)
        np.testing.assert_array_equal(
            predictor.encode(u.astype(np.float32), y),
            predictor.encode(u.astype(np.float32).astype(np.float64), y))
