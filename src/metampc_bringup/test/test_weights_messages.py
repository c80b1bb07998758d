"""The models to control with, decoded again as the controller decodes them."""
import math

from metampc_model.manual_model import linearised_vdp_nssm
from metampc_model.nssm import Nssm
from metampc_model.weights_codec import fields_of, weights_from_fields
from metampc_learner.checkpoint import save_checkpoint
import numpy as np

from metampc_bringup.soak.weights_messages import checkpoint_weights, manual_weights


def test_manual_model_is_the_zoh_oscillator_at_theta_0():
    dt = 0.1
    msg = manual_weights(0.0, dt, version=3, n_z=5, hidden=(128, 128))
    assert (msg.version, msg.method, msg.stage) == (3, 'manual', 'adapted')
    decoded = weights_from_fields(fields_of(msg))
    assert (decoded.config.n_z, decoded.config.hidden, decoded.config.history) == (
        5, (128, 128), 10)
    # x1' = x2, x2' = -x1 + u held over dt: a rotation by dt, and B = (1 - cos dt, sin dt)
    c, s = math.cos(dt), math.sin(dt)
    a = decoded.params['A']
    np.testing.assert_allclose(a[:2, :2], [[c, s], [-s, c]], atol=1e-6)
    np.testing.assert_allclose(decoded.params['B'][:2, 0], [1 - c, s], atol=1e-6)


def test_checkpoint_keeps_its_weights_method_and_stage(tmp_path):
    config, norm, params = linearised_vdp_nssm(0.5, 0.05)
    path = str(tmp_path / 'model.pt')
    save_checkpoint(path, Nssm(config, norm), params, {'method': 'maml', 'stage': 'meta'})
    msg = checkpoint_weights(path)
    assert (msg.version, msg.method, msg.stage) == (1, 'maml', 'meta')
    decoded = weights_from_fields(fields_of(msg))
    assert decoded.config == config
    for name, value in params.items():
        assert np.array_equal(decoded.params[name], value.numpy())
    save_checkpoint(path, Nssm(config, norm), params)
    assert (checkpoint_weights(path).method, checkpoint_weights(path).stage) == (
        'imaml', 'adapted')
