"""The feature NARX's meta-training and adaptation (narx_learning)."""
import numpy as np
import pytest
import torch

from metampc_learner.closed_form import mean_loss, ridge
from metampc_learner.narx_learning import (adapt, arx_model, meta_train, NarxMetaConfig,
                                           one_step_data, outer_loss)
from metampc_model.feature_narx import (FeatureNarx, init_params, NarxShape, regressors,
                                        rollout)
from metampc_model.normalisation import Normalisation


def _random_meta(shape, seed, norm=None):
    params = init_params(shape, seed)
    gen = torch.Generator().manual_seed(seed + 7)
    params['head'] = torch.randn(params['head'].shape, generator=gen, dtype=torch.float64)
    norm = norm or Normalisation(np.zeros(shape.n_u), np.ones(shape.n_u), np.zeros(shape.n_y),
                                 np.ones(shape.n_y))
    return FeatureNarx(shape, norm, params)


def _arx2_records(seed, n=300, noise=0.0):
    """A plant that is exactly an ARX(2), 2 outputs, 1 input (stable), and its coefficients
    [a_1, a_2, b_1 (u_t), b_0 (u_{t+1}), c] as the head's linear columns."""
    rng = np.random.default_rng(seed)
    a1 = np.array([[0.5, 0.2], [-0.1, 0.6]])
    a2 = np.array([[0.1, 0.0], [0.05, -0.2]])
    b0, b1, c = np.array([1.0, -0.5]), np.array([0.3, 0.2]), np.array([0.1, -0.3])
    u = rng.uniform(-1, 1, (n, 1))
    y = np.zeros((n, 2))
    for t in range(2, n):
        y[t] = a1 @ y[t - 1] + a2 @ y[t - 2] + b0 * u[t, 0] + b1 * u[t - 1, 0] + c
        y[t] += noise * rng.normal(size=2)
    return [(u, y)], np.hstack([a1, a2, b1[:, None], b0[:, None], c[:, None]])


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_an_exact_arx2_plant_is_recovered_from_any_meta_model(seed):
    records, theta = _arx2_records(seed)
    shape = NarxShape(1, 2, order=2, features=6, hidden=(8,))
    adapted = adapt(_random_meta(shape, seed), records, gamma=1e-3)
    head = adapted.model.params['head'].numpy()
    lin = np.r_[0:shape.n_s, shape.n_s + shape.features:shape.n_phi]
    np.testing.assert_allclose(head[:, lin], theta, atol=1e-6)
    np.testing.assert_allclose(head[:, shape.n_s:shape.n_s + shape.features], 0, atol=1e-6)


@pytest.mark.parametrize('seed', range(6))
def test_the_adapted_training_loss_is_never_above_the_arxs(seed):
    rng = np.random.default_rng(seed)
    records, _ = _arx2_records(seed, n=120, noise=float(rng.uniform(0, 0.2)))
    u, y = records[0]
    y = y + 0.3 * np.tanh(np.roll(y, 1, axis=0))            # not an ARX any more
    shape = NarxShape(1, 2, order=2, features=4, hidden=(5,))
    meta = _random_meta(shape, seed)
    for gamma in (0.0, 1e-6, 1e-2, 10.0):
        adapted = adapt(meta, [(u, y)], gamma)
        phi, target = one_step_data(shape, meta.params, meta.norm, [(u, y)])
        arx = arx_model(meta, [(u, y)])
        arx_loss = float(mean_loss(phi, target, arx.params['head']))
        assert adapted.arx_loss == pytest.approx(arx_loss, rel=1e-12)
        assert adapted.train_loss <= arx_loss
        assert adapted.train_loss == pytest.approx(
            float(mean_loss(phi, target, adapted.model.params['head'])), rel=1e-12)


def test_a_strong_prior_that_loses_to_the_arx_is_dropped():
    records, theta = _arx2_records(0)
    shape = NarxShape(1, 2, order=2, features=3, hidden=(4,))
    adapted = adapt(_random_meta(shape, 0), records, gamma=1e3)
    assert adapted.rule == 'ridge_to_arx'
    adapted = adapt(_random_meta(shape, 0), records, gamma=1e-12)
    assert adapted.rule in ('ridge', 'ridge_to_arx')


def test_the_ridge_to_arx_stays_regularised_where_features_are_collinear_with_the_lags():
    """Features that are (nearly) linear in the lags on the samples: plain least squares
    gives a head whose feature and lag columns cancel on the data with large weights; the
    ridge toward the ARX's head ('ridge_to_arx') keeps them near the ARX's (fails on gamma = 0
    there)."""
    records, theta = _arx2_records(4, noise=1e-2)
    shape = NarxShape(1, 2, order=2, features=3, hidden=(4,))
    meta = _random_meta(shape, 4)
    for name in ('g.0.weight', 'g.1.weight'):
        meta.params[name] = meta.params[name] * 0.1        # tanh near its linear range
    adapted = adapt(meta, records, gamma=1e3)
    assert adapted.rule == 'ridge_to_arx'
    head = adapted.model.params['head'].numpy()
    assert np.abs(head).max() < 10 * np.abs(theta).max()


def _toy_systems(ks, seed):
    """Scalar systems y+ = 0.7 y + 0.5 k tanh(2 y) + 0.5 u with task parameters `ks`."""
    rng = np.random.default_rng(seed)
    out = []
    for k in ks:
        u = rng.uniform(-1, 1, (80, 1))
        y = np.zeros((80, 1))
        for t in range(1, 80):
            y[t] = 0.7 * y[t - 1] + 0.5 * k * np.tanh(2 * y[t - 1]) + 0.5 * u[t]
        out.append([(u, y)])
    return out


def test_imaml_meta_gradient_is_the_exact_gradient_through_the_solve():
    """One outer step's loss gradient (what meta_train backpropagates) against central
    differences of the same outer loss in a head entry and a feature weight."""
    shape = NarxShape(1, 1, order=1, features=3, hidden=(4,))
    params = _random_meta(shape, 3).params
    rng = np.random.default_rng(0)
    s_tr, u_tr, y_tr = (torch.from_numpy(rng.normal(size=sz)) for sz in
                        ((20, 1), (20, 1), (20, 1)))
    s_te, u_te, y_te = (torch.from_numpy(rng.normal(size=sz)) for sz in
                        ((10, 1), (10, 1), (10, 1)))

    def outer(p):
        head = ridge(regressors(shape, p, s_tr, u_tr), y_tr, p['head'], 0.5)
        return (regressors(shape, p, s_te, u_te) @ head.T - y_te).square().sum(-1).mean()

    leaves = {k: v.clone().requires_grad_() for k, v in params.items()}
    outer(leaves).backward()
    for name, idx in (('head', (0, 2)), ('g.0.weight', (1, 0))):
        eps = 1e-6
        plus = {k: v.clone() for k, v in params.items()}
        minus = {k: v.clone() for k, v in params.items()}
        plus[name][idx] += eps
        minus[name][idx] -= eps
        fd = (float(outer(plus)) - float(outer(minus))) / (2 * eps)
        assert float(leaves[name].grad[idx]) == pytest.approx(fd, rel=1e-5, abs=1e-9)


def test_first_order_maml_gradient_is_the_outer_gradient_at_the_adapted_head():
    """Eq. (outer_maml): the value is the outer loss at the head solved with maml_gamma (a dense
    least squares here), the gradient the outer loss's with that head held fixed, to a feature
    weight by its direct path and to the prior head as to the adapted one (central differences
    of that loss). Fails on the exact gradient through the solve (iMAML's) and on the solve
    with `gamma` in place of `maml_gamma`."""
    shape = NarxShape(1, 1, order=1, features=3, hidden=(4,))
    params = _random_meta(shape, 3).params
    rng = np.random.default_rng(1)
    s_tr, y_tr, s_te, y_te = (torch.from_numpy(rng.normal(size=(2, n, 1))) for n in (20, 20, 6, 6))
    u_tr, u_te = (torch.from_numpy(rng.normal(size=(2, n, 1, 1))) for n in (20, 6))
    s_te, u_te, y_te = s_te, torch.cat([u_te, u_te], -2), torch.stack([y_te, -y_te], -2)
    config = NarxMetaConfig(method='maml', gamma=1e-6, maml_gamma=0.5)
    phi = regressors(shape, params, s_tr, u_tr[..., 0, :]).numpy()
    gram = np.einsum('bmi,bmj->bij', phi, phi) / 20 + 0.25 * np.eye(shape.n_phi)
    rhs = np.einsum('bmi,bmj->bij', phi, y_tr.numpy()) / 20 + 0.25 * params['head'].numpy().T
    adapted = torch.from_numpy(np.linalg.solve(gram, rhs).transpose(0, 2, 1))

    def at_adapted(p, head):                  # the outer loss, the head held at `head`
        y_hat = rollout(shape, p, s_te, u_te, head[:, None])
        return float((y_hat - y_te).square().sum(-1).mean())

    leaves = {k: v.clone().requires_grad_() for k, v in params.items()}
    loss = outer_loss(shape, leaves, (s_tr, u_tr, y_tr[..., None, :]), (s_te, u_te, y_te),
                      config)
    assert float(loss.detach()) == pytest.approx(at_adapted(params, adapted), rel=1e-10)
    loss.backward()
    eps = 1e-6
    plus, minus = ({k: v.clone() for k, v in params.items()} for _ in range(2))
    plus['g.0.weight'][1, 0] += eps
    minus['g.0.weight'][1, 0] -= eps
    fd = (at_adapted(plus, adapted) - at_adapted(minus, adapted)) / (2 * eps)
    assert float(leaves['g.0.weight'].grad[1, 0]) == pytest.approx(fd, rel=1e-5, abs=1e-9)
    step = torch.zeros_like(adapted)
    step[:, 0, 2] = eps                       # every task's adapted head moved alike
    fd = (at_adapted(params, adapted + step) - at_adapted(params, adapted - step)) / (2 * eps)
    assert float(leaves['head'].grad[0, 2]) == pytest.approx(fd, rel=1e-5, abs=1e-9)


def test_first_order_maml_near_the_meta_model_learns_where_the_exact_solve_does_not():
    """First-order MAML on the toy family: with its inner solve kept near the meta-model
    (maml_gamma 0.1) the D_test loss falls and the adapted fits beat the ARX on unseen systems;
    with the inner solve at the adaptation's strength (1e-4), where d psi / d omega = I is
    wrong, the D_test loss rises (measured: 4.5e-3 -> 2.3e-2)."""
    systems = _toy_systems(np.random.default_rng(5).normal(size=30), 0)
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(1), np.ones(1))
    shape = NarxShape(1, 1, order=1, features=4, hidden=(16,))
    config = NarxMetaConfig(method='maml', iterations=150, batch_size=8, windows=32, horizon=5,
                            lr=1e-2, gamma=1e-4, maml_gamma=0.1)
    res = meta_train(shape, norm, systems, config)
    assert np.mean(res.curve[-10:]) < 0.5 * np.mean(res.curve[:10])
    meta = FeatureNarx(shape, norm, res.params)
    for records in _toy_systems([-1.2, -0.8, 0.8, 1.2, 1.5], 99):
        adapted = adapt(meta, records, 1e-4)
        assert adapted.train_loss < 0.5 * adapted.arx_loss
    exact = meta_train(shape, norm, systems, NarxMetaConfig(**{**config.__dict__,
                                                               'maml_gamma': 1e-4}))
    assert np.mean(exact.curve[-10:]) > np.mean(exact.curve[:10])


def test_imaml_meta_training_learns_features_that_beat_the_arx_on_unseen_systems():
    systems = _toy_systems(np.random.default_rng(5).normal(size=30), 0)
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(1), np.ones(1))
    shape = NarxShape(1, 1, order=1, features=4, hidden=(16,))
    res = meta_train(shape, norm, systems, NarxMetaConfig(method='imaml', iterations=150,
                                                          batch_size=8, windows=32,
                                                          horizon=5, lr=1e-2, gamma=1e-4))
    assert np.mean(res.curve[-10:]) < 0.5 * np.mean(res.curve[:10])
    meta = FeatureNarx(shape, norm, res.params)
    # unseen systems where the nonlinearity matters (|k| >= 0.8): the ARX averages it
    for records in _toy_systems([-1.2, -0.8, 0.8, 1.2, 1.5], 99):
        adapted = adapt(meta, records, 1e-4)
        assert adapted.train_loss < 0.5 * adapted.arx_loss


def test_features_that_fit_the_noise_lose_the_validation_and_the_arx_flies():
    """An ARX(2) plant with noise and many random, steep features: the fit wins on its own
    samples (lower training loss) and loses to the ARX on the held-back part, so the ARX's
    head flies (fails without the validation: rule 'ridge' or 'ridge_to_arx')."""
    records, theta = _arx2_records(5, n=120, noise=0.3)
    shape = NarxShape(1, 2, order=2, features=40, hidden=(40,))
    meta = _random_meta(shape, 5)
    for name in ('g.0.weight', 'g.1.weight'):
        meta.params[name] = meta.params[name] * 8.0
    adapted = adapt(meta, records, gamma=1e-6)
    assert adapted.rule == 'arx_validated'
    assert adapted.train_loss == adapted.arx_loss
    np.testing.assert_allclose(adapted.model.params['head'].numpy(),
                               arx_model(meta, records).params['head'].numpy())
