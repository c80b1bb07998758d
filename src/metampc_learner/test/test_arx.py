"""The ARX baseline: least squares recovers a known ARX, and its NSSM predicts what it does."""
import numpy as np
import pytest
import torch

from metampc_learner.arx import arx_nssm, as_nssm, equilibrium, fit
from metampc_learner.data import Trajectory
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_model.predictor import NssmPredictor


def known_arx(order, n_y, n_u, seed):
    """A stable ARX(order): a_i scaled so that the companion matrix has radius < 1."""
    rng = np.random.default_rng(seed)
    a = [rng.normal(size=(n_y, n_y)) * 0.3 / (i + 1) for i in range(order)]
    b = [rng.normal(size=(n_y, n_u)) for _ in range(order)]
    c = rng.normal(size=n_y)
    return a, b, c


def simulate(a, b, c, u, y0):
    """y_t of the ARX from the first len(a) outputs y0 under inputs u (u_t produced y_t)."""
    p = len(a)
    y = np.zeros((len(u), c.size))
    y[:p] = y0
    for t in range(p, len(u)):
        y[t] = c + sum(a[i] @ y[t - 1 - i] for i in range(p)) + sum(
            b[j] @ u[t - j] for j in range(p))
    return y


def companion_radius(a):
    n_y, p = a[0].shape[0], len(a)
    top = np.hstack(a)
    low = np.eye(n_y * (p - 1), n_y * p) if p > 1 else np.zeros((0, n_y))
    return max(abs(np.linalg.eigvals(np.vstack([top, low]))))


@pytest.mark.parametrize('order,n_y,n_u', [(1, 2, 1), (2, 2, 2), (3, 1, 1)])
def test_fit_recovers_a_noise_free_arx(order, n_y, n_u):
    a, b, c = known_arx(order, n_y, n_u, seed=order)
    assert companion_radius(a) < 1.0
    rng = np.random.default_rng(7)
    parts = []
    for k in range(3):          # trajectories are fitted separately: no cross-boundary rows
        u = rng.uniform(-1, 1, size=(80, n_u))
        parts.append(Trajectory(np.arange(80) + 1000 * k, u,
                                simulate(a, b, c, u, rng.normal(size=(order, n_y)))))
    a_hat, b_hat, c_hat = fit(parts, order)
    for got, want in zip(a_hat + b_hat, a + b):
        np.testing.assert_allclose(got, want, atol=1e-9)
    np.testing.assert_allclose(c_hat, c, atol=1e-9)


def test_too_few_samples_is_one_clear_error():
    traj = Trajectory(np.arange(5), np.zeros((5, 1)), np.zeros((5, 2)))
    with pytest.raises(ValueError, match='equations'):
        fit([traj], 2)


@pytest.mark.parametrize('hidden', [(16, 16), (), (12,)])
def test_the_nssm_predicts_exactly_what_the_arx_does(hidden):
    order, n_y, n_u, hist = 2, 2, 2, 4
    a, b, c = known_arx(order, n_y, n_u, seed=3)
    base = NssmConfig(n_u=n_u, n_y=n_y, n_z=5, history=hist, hidden=hidden, loss_horizon=6)
    scale = Normalisation(np.zeros(n_u), np.array([2.0, 0.5]), np.zeros(n_y),
                          np.array([3.0, 0.7]))
    u_s = np.array([0.3, -0.2])
    config, norm, params = as_nssm(a, b, c, u_s, base, scale)
    assert config.n_z == order * n_y + (order - 1) * n_u and not config.stable_latent
    np.testing.assert_allclose(norm.u_mean, u_s)
    y_s = norm.y_mean          # an equilibrium of the ARX
    np.testing.assert_allclose(y_s, sum(a) @ y_s + sum(b) @ u_s + c, atol=1e-12)
    rng = np.random.default_rng(11)
    u = rng.uniform(-1, 1, size=(30, n_u))
    y = simulate(a, b, c, u, rng.normal(size=(order, n_y)))
    predictor = NssmPredictor(config, norm, params)
    t = 12
    got = predictor.predict(u[t - hist + 1:t + 1], y[t - hist + 1:t + 1], u[t + 1:t + 7])
    np.testing.assert_allclose(got, y[t + 1:t + 7], rtol=1e-5, atol=1e-5)   # float32 weights
    model = Nssm(config, norm)          # the torch model, normalised windows
    u_n, y_n = norm.normalise(u[None, t - hist + 1:t + 7], y[None, t - hist + 1:t + 7])
    y_hat = torch.func.functional_call(model, params, (torch.tensor(u_n, dtype=torch.float32),
                                                       torch.tensor(y_n, dtype=torch.float32)))
    np.testing.assert_allclose(norm.denormalise_y(y_hat.detach().numpy()[0]), y[t + 1:t + 7],
                               rtol=1e-4, atol=1e-4)


def test_arx_nssm_refuses_what_it_cannot_write():
    traj = Trajectory(np.arange(50), np.random.default_rng(0).normal(size=(50, 1)),
                      np.random.default_rng(1).normal(size=(50, 2)))
    scale = Normalisation(np.zeros(1), np.ones(1), np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match='history H is 2'):
        arx_nssm([traj], 3, NssmConfig(n_u=1, n_y=2, history=2, hidden=(32,)), scale)
    with pytest.raises(ValueError, match='at least 10 units'):
        arx_nssm([traj], 2, NssmConfig(n_u=1, n_y=2, history=4, hidden=(8,)), scale)
    with pytest.raises(ValueError, match='pole at 1'):
        equilibrium([np.eye(2)], [np.ones((2, 1))], np.zeros(2), np.zeros(1))


def test_the_nssm_of_an_arx_of_order_3_predicts_exactly_what_the_arx_does():
    """Order 3: z_t holds u_t and u_{t-1}, so the companion matrix shifts the inputs too
    (at order 2 there is one input in z and no shift to get wrong)."""
    order, n_y, n_u, hist = 3, 1, 2, 5
    a, b, c = known_arx(order, n_y, n_u, seed=5)
    assert companion_radius(a) < 1.0
    base = NssmConfig(n_u=n_u, n_y=n_y, n_z=7, history=hist, hidden=(16,), loss_horizon=6)
    scale = Normalisation(np.zeros(n_u), np.array([2.0, 0.5]), np.zeros(n_y), np.array([3.0]))
    config, norm, params = as_nssm(a, b, c, np.array([0.3, -0.2]), base, scale)
    assert config.n_z == 3 * n_y + 2 * n_u
    rng = np.random.default_rng(12)
    u = rng.uniform(-1, 1, size=(30, n_u))
    y = simulate(a, b, c, u, rng.normal(size=(order, n_y)))
    predictor = NssmPredictor(config, norm, params)
    t = 12
    got = predictor.predict(u[t - hist + 1:t + 1], y[t - hist + 1:t + 1], u[t + 1:t + 9])
    np.testing.assert_allclose(got, y[t + 1:t + 9], rtol=1e-5, atol=1e-5)   # float32 weights
