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


def test_without_the_fit_toward_the_arx_a_losing_prior_flies_the_arxs_own_head():
    """toward_arx False: where the fit toward the meta-model loses to the ARX on the samples
    the head is the least-squares ARX's, its feature columns zero (fails on a version that
    still fits toward the ARX with the features free: rule 'ridge_to_arx'); elsewhere the
    rule is the same."""
    records, _ = _arx2_records(0)
    shape = NarxShape(1, 2, order=2, features=3, hidden=(4,))
    adapted = adapt(_random_meta(shape, 0), records, gamma=1e3, toward_arx=False)
    assert adapted.rule == 'arx'
    torch.testing.assert_close(adapted.model.params['head'],
                               arx_model(_random_meta(shape, 0), records).params['head'])
    assert adapted.train_loss == pytest.approx(adapted.arx_loss, rel=1e-12)
    noisy, _ = _arx2_records(1, noise=1e-2)
    both = [adapt(_random_meta(shape, 1), noisy, gamma=1e-12, toward_arx=flag).rule
            for flag in (True, False)]
    assert both[0] != 'ridge_to_arx' and both[0] == both[1]


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


def _split_batch(seed):
    """A batch of 2 tasks: D_tr's 12 one-step windows and D_test's 5 windows of T = 2."""
    rng = np.random.default_rng(seed)
    s_tr, y_tr, s_te = (torch.from_numpy(rng.normal(size=(2, n, 1))) for n in (12, 12, 5))
    u_tr, u_te, y_te = (torch.from_numpy(rng.normal(size=(2, n, k, 1)))
                        for n, k in ((12, 1), (5, 2), (5, 2)))
    return (s_tr, u_tr, y_tr[..., None, :]), (s_te, u_te, y_te)


def _central(f, params, name, idx, eps=1e-6):
    plus, minus = ({k: v.clone() for k, v in params.items()} for _ in range(2))
    plus[name][idx] += eps
    minus[name][idx] -= eps
    return (f(plus) - f(minus)) / (2 * eps)


def test_first_order_maml_gradient_is_exact_by_the_envelope_theorem():
    """'maml' (variable projection): the value is min over the head of the one-step loss on
    all of a task's one-step equations (D_tr's and D_test's first steps) + gamma/2 ||Theta -
    Theta_bar||^2, solved densely here; its first-order gradient (no gradient through the
    solve) equals central differences of that minimum, the head solved again at each point,
    in a feature weight and the prior head. Fails on the loss without the prior term, on the
    support D_tr only, on the head solved at another strength than the loss's, and on the
    prior term's gradient dropped (its prior detached)."""
    shape = NarxShape(1, 1, order=1, features=3, hidden=(4,))
    params = _random_meta(shape, 3).params
    train, test = _split_batch(1)
    gamma = 0.3
    config = NarxMetaConfig(method='maml', gamma=gamma)
    s = torch.cat([train[0], test[0]], 1)
    u, y = (torch.cat([train[i][..., 0, :], test[i][..., 0, :]], 1) for i in (1, 2))

    def minimum(p):                           # dense: the objective at its minimiser, per task
        phi, out = regressors(shape, p, s, u).numpy(), y.numpy()
        prior = p['head'].numpy()[0]
        total = 0.0
        for b in range(2):
            m = len(phi[b])
            head = np.linalg.solve(phi[b].T @ phi[b] / m + gamma / 2 * np.eye(shape.n_phi),
                                   phi[b].T @ out[b][:, 0] / m + gamma / 2 * prior)
            total += (np.mean((out[b][:, 0] - phi[b] @ head) ** 2)
                      + gamma / 2 * np.sum((head - prior) ** 2))
        return total / 2

    leaves = {k: v.clone().requires_grad_() for k, v in params.items()}
    loss = outer_loss(shape, leaves, train, test, config)
    assert float(loss.detach()) == pytest.approx(minimum(params), rel=1e-10)
    loss.backward()
    for name, idx in (('g.0.weight', (1, 0)), ('head', (0, 2)), ('head', (0, 0))):
        fd = _central(minimum, params, name, idx)
        assert float(leaves[name].grad[idx]) == pytest.approx(fd, rel=1e-5, abs=1e-9)


def test_the_first_order_gradient_of_a_query_loss_is_not_the_exact_one():
    """Where the loss is not the inner problem's own (iMAML's: the T-step rollout on D_test
    at the head solved on D_tr) the partial gradient at the held head misses the head's
    sensitivity: against autograd through the solve (the exact gradient, central differences
    in test_imaml_meta_gradient_is_the_exact_gradient_through_the_solve) its error is large,
    where the envelope theorem makes the 'maml' one exact. Fails on iMAML's loss made first
    order (its solve detached)."""
    shape = NarxShape(1, 1, order=1, features=3, hidden=(4,))
    params = _random_meta(shape, 3).params
    train, test = _split_batch(1)
    config = NarxMetaConfig(method='imaml', gamma=0.3)

    def gradient(first_order):
        leaves = {k: v.clone().requires_grad_() for k, v in params.items()}
        if first_order:
            with torch.no_grad():
                phi = regressors(shape, leaves, train[0], train[1][..., 0, :])
                head = ridge(phi, train[2][..., 0, :], leaves['head'], config.gamma)
            y_hat = rollout(shape, leaves, test[0], test[1], head[:, None])
            loss = (y_hat - test[2]).square().sum(-1).mean()
        else:
            loss = outer_loss(shape, leaves, train, test, config)
        loss.backward()
        return leaves['g.0.weight'].grad.flatten()

    exact, first = gradient(False), gradient(True)
    assert float((first - exact).norm() / exact.norm()) > 0.1


@pytest.mark.parametrize('method', ['maml', 'imaml'])
def test_meta_training_learns_features_that_beat_the_arx_on_unseen_systems(method):
    """On the toy family, each method (first-order MAML by variable projection, its inner
    solve at the adaptation's strength; iMAML through the solve): the meta-training loss falls
    and the adapted fits beat the ARX on unseen systems."""
    systems = _toy_systems(np.random.default_rng(5).normal(size=30), 0)
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(1), np.ones(1))
    shape = NarxShape(1, 1, order=1, features=4, hidden=(16,))
    res = meta_train(shape, norm, systems, NarxMetaConfig(method=method, iterations=150,
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
