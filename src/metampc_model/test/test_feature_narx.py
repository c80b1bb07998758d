"""The feature NARX: one step, rollout, state windows and the linearisation (feature_narx)."""
import numpy as np
import pytest
import torch

from metampc_model.feature_narx import (FeatureNarx, init_params, NarxShape, rollout,
                                        state_windows)
from metampc_model.normalisation import Normalisation


def _model(order=3, n_u=2, n_y=2, features=5, seed=0):
    shape = NarxShape(n_u, n_y, order, features, (7,))
    params = init_params(shape, seed)
    gen = torch.Generator().manual_seed(seed + 1)
    params['head'] = torch.randn(params['head'].shape, generator=gen, dtype=torch.float64) * 0.3
    norm = Normalisation(np.array([0.1, -0.2][:n_u]), np.array([0.5, 2.0][:n_u]),
                         np.array([0.3, 1.0][:n_y]), np.array([1.5, 0.7][:n_y]))
    return FeatureNarx(shape, norm, params)


def test_the_linearisation_matches_central_differences_of_the_one_step_map():
    model = _model()
    rng = np.random.default_rng(3)
    s, u = rng.normal(size=model.shape.n_s), rng.normal(size=2)
    lin = model.linearise(s, u)

    def full_step(s, u):       # the state map s -> s+ the linearisation describes
        y = model.step(s, u)
        return np.concatenate([y, s[:2 * 2], u, s[3 * 2:3 * 2 + 2]])

    eps = 1e-6
    jac_s = np.stack([(full_step(s + eps * e, u) - full_step(s - eps * e, u)) / (2 * eps)
                      for e in np.eye(s.size)], axis=1)
    jac_u = np.stack([(full_step(s, u + eps * e) - full_step(s, u - eps * e)) / (2 * eps)
                      for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(lin.A, jac_s, atol=1e-7)
    np.testing.assert_allclose(lin.B, jac_u, atol=1e-7)
    # exact at the point itself: z+ = A s + B u + e is the model's step there
    np.testing.assert_allclose(lin.step(s, u), full_step(s, u), atol=1e-12)
    np.testing.assert_allclose(lin.output(s), s[:2])


def test_order_one_has_no_input_lags():
    model = _model(order=1, n_u=1, n_y=2)
    assert model.shape.n_s == 2
    lin = model.linearise(np.array([0.2, -0.1]), np.array([0.3]))
    np.testing.assert_allclose(lin.step(np.array([0.2, -0.1]), np.array([0.3])),
                               model.step(np.array([0.2, -0.1]), np.array([0.3])), atol=1e-12)


def test_rollout_feeds_its_own_predictions_and_the_inputs_into_the_lags():
    model = _model(order=2, n_u=1, n_y=1, features=3)
    sh, p = model.shape, model.params
    rng = np.random.default_rng(0)
    s, u = rng.normal(size=(4, sh.n_s)), rng.normal(size=(4, 5, 1))
    by_rollout = rollout(sh, p, torch.from_numpy(s), torch.from_numpy(u)).numpy()
    nm = Normalisation(np.zeros(1), np.ones(1), np.zeros(1), np.ones(1))
    plain = FeatureNarx(sh, nm, p)
    for b in range(4):        # step by step in the physical (here: identity) units
        y_prev, y_now, u_now = s[b, 1], s[b, 0], s[b, 2]
        for k in range(5):
            y_next = plain.step(np.array([y_now, y_prev, u_now]), u[b, k])[0]
            assert by_rollout[b, k, 0] == pytest.approx(y_next, abs=1e-12)
            y_prev, y_now, u_now = y_now, y_next, u[b, k, 0]


def test_state_windows_follow_the_data_convention():
    shape = NarxShape(1, 1, order=3, features=0)
    u = np.arange(10.0)[:, None] + 100
    y = np.arange(10.0)[:, None]
    s, uf, yf = state_windows(shape, u, y, horizon=2)
    assert s.shape == (6, 5) and uf.shape == (6, 2, 1)
    np.testing.assert_array_equal(s[0], [2, 1, 0, 102, 101])   # y_t..y_{t-2}, u_t, u_{t-1}
    np.testing.assert_array_equal(uf[0, :, 0], [103, 104])      # u_{t+1}, u_{t+2}
    np.testing.assert_array_equal(yf[-1, :, 0], [8, 9])


def test_a_non_finite_jacobian_is_refused():
    model = _model()
    model.params['head'][0, 0] = float('inf')
    with pytest.raises(ValueError, match='non-finite'):
        model.linearise(np.zeros(model.shape.n_s), np.zeros(2))


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match='order'):
        NarxShape(1, 1, order=0)
