"""The proximal inner problem in closed form (closed_form)."""
import warnings

import numpy as np
import pytest
import torch

from metampc_learner.closed_form import mean_loss, ridge


@pytest.mark.parametrize('gamma', [0.0, 0.3])
def test_the_closed_form_equals_a_dense_least_squares(gamma):
    rng = np.random.default_rng(1)
    phi, y = rng.normal(size=(50, 6)), rng.normal(size=(50, 3))
    prior = rng.normal(size=(3, 6))
    got = ridge(torch.from_numpy(phi), torch.from_numpy(y), torch.from_numpy(prior),
                gamma).numpy()
    # min 1/M ||Y - Phi Theta'||^2 + gamma/2 ||Theta - prior||^2 as one stacked lstsq
    k = np.sqrt(gamma / 2)
    lhs = np.vstack([phi / np.sqrt(50), k * np.eye(6)])
    rhs = np.vstack([y / np.sqrt(50), k * prior.T])
    want = np.linalg.lstsq(lhs, rhs, rcond=None)[0].T
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_the_closed_form_is_batched():
    rng = np.random.default_rng(2)
    phi, y, prior = (torch.from_numpy(rng.normal(size=s)) for s in
                     ((4, 30, 5), (4, 30, 2), (2, 5)))
    batched = ridge(phi, y, prior, 0.1)
    for b in range(4):
        torch.testing.assert_close(batched[b], ridge(phi[b], y[b], prior, 0.1))


def test_collinear_samples_warn_once_and_stay_finite():
    phi = torch.ones((40, 3), dtype=torch.float64)        # a constant input beside the bias
    phi[:, 0] = torch.linspace(-1, 1, 40, dtype=torch.float64)
    y = 2 * phi[:, :1]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        head = ridge(phi, y, torch.zeros((1, 3), dtype=torch.float64), 0.0)
    assert len([w for w in caught if 'collinear' in str(w.message)]) == 1
    assert torch.all(torch.isfinite(head))
    assert float(mean_loss(phi, y, head)) < 1e-12


def test_nearly_collinear_lags_keep_the_least_squares_fit():
    """The ARX(2) of a van der Pol record (theta 0.03, held inputs): its outputs are a state
    and its derivative, so the lags are nearly collinear (cond(Phi) ~ 3e5, cond(Phi'Phi)
    ~ 8e10). gamma 0 must give the least-squares loss (numpy's lstsq, SVD) to 1e-4; the
    normal equations with a floor of 1e-10 of the mean diagonal gave 42x it."""
    from metampc_plant.integrate import rk4_sample
    from metampc_plant.registry import get_family
    fam, rng = get_family('vanderpol'), np.random.default_rng(0)
    x, xs, us = np.array([0.5, 0.0]), [np.array([0.5, 0.0])], []
    for k in range(301):
        u = rng.uniform(-1, 1, size=1) if k % 5 == 0 else us[-1]
        x = rk4_sample(fam, x[None], u[None], np.array([[0.03]]), 0.1, 10)[0]
        us.append(u)
        xs.append(x)
    xs, us = np.array(xs), np.array(us)
    phi = np.hstack([xs[1:-1], xs[:-2], us[1:], us[:-1]])
    phi = np.hstack([(phi - phi.mean(0)) / phi.std(0), np.ones((300, 1))])
    y = xs[2:]
    assert np.linalg.cond(phi) > 1e5
    want = np.linalg.lstsq(phi, y, rcond=None)[0].T
    got = ridge(torch.from_numpy(phi), torch.from_numpy(y),
                torch.zeros((2, 7), dtype=torch.float64), 0.0)
    best = float(mean_loss(torch.from_numpy(phi), torch.from_numpy(y), torch.from_numpy(want)))
    assert float(mean_loss(torch.from_numpy(phi), torch.from_numpy(y), got)) <= best * (1 + 1e-4)


def test_the_gradient_through_the_solve_equals_finite_differences():
    """Autograd through the QR solve (meta-training differentiates it): d loss / d phi."""
    rng = np.random.default_rng(3)
    phi = torch.from_numpy(rng.normal(size=(20, 4))).requires_grad_(True)
    y = torch.from_numpy(rng.normal(size=(20, 2)))
    prior = torch.from_numpy(rng.normal(size=(2, 4)))
    torch.autograd.gradcheck(lambda p: ridge(p, y, prior, 0.2), (phi,))
