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
