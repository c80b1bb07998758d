"""The head refined on the simulation error (output_error), against answers known beforehand:
a model of the class recovered from a wrong head, and the equation error's bias under output
noise (an ARX(1): least squares attenuates the pole, the simulation error does not)."""
import numpy as np
import pytest
import torch

from metampc_learner.output_error import OutputErrorConfig, refine_head
from metampc_model.feature_narx import FeatureNarx, init_params, rollout
from metampc_model.narx_shape import NarxShape
from metampc_model.normalisation import Normalisation


def identity(n_u: int = 1, n_y: int = 1) -> Normalisation:
    return Normalisation(np.zeros(n_u), np.ones(n_u), np.zeros(n_y), np.ones(n_y))


def simulate(model: FeatureNarx, u: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """The model's own free run from the first p samples y0 (p, n_y) under inputs u (K, n_u)
    (identity normalisation): y (K, n_y)."""
    p = model.shape.order
    s = np.concatenate([y0[p - 1 - i] for i in range(p)] + [u[p - 1 - j] for j in range(p - 1)])
    with torch.no_grad():
        run = rollout(model.shape, model.params, torch.from_numpy(s[None]),
                      torch.from_numpy(u[None, p:]))[0].numpy()
    return np.concatenate([y0, run])


def test_a_model_of_the_class_is_recovered_from_a_wrong_head():
    """Records simulated by a feature NARX (p 2, F 4): from its head moved by 20 %, the fit
    returns it (fails without the Jacobian's transpose, or a step taken though L rose)."""
    shape = NarxShape(1, 1, order=2, features=4, hidden=(8,))
    params = init_params(shape, 0)
    head = torch.zeros((1, shape.n_phi), dtype=torch.float64)
    head[0, :2] = torch.tensor([1.2, -0.5])           # a stable second-order lag part
    head[0, 3:7] = 0.05 * torch.arange(1, 5)          # the features
    head[0, 7] = 0.3                                  # u_{t+1}
    truth = FeatureNarx(shape, identity(), {**params, 'head': head})
    rng = np.random.default_rng(0)
    records = []
    for _ in range(2):
        u = np.repeat(rng.uniform(-1, 1, 40), 5)[:, None]
        records.append((u, simulate(truth, u, np.zeros((2, 1)))))
    wrong = FeatureNarx(shape, identity(), {**params, 'head': head * (
        1 + 0.2 * torch.from_numpy(rng.standard_normal(head.shape)))})
    fit = refine_head(wrong, records, OutputErrorConfig(iterations=100, rtol=0.0))
    assert fit.loss_start > 1e-4 and fit.loss < 1e-20
    np.testing.assert_allclose(fit.model.params['head'].numpy(), head.numpy(), atol=1e-7)
    assert all(b < a for a, b in zip(fit.curve, fit.curve[1:]))


def test_under_output_noise_the_simulation_error_is_not_biased_where_least_squares_is():
    """x+ = 0.9 x + 0.5 u+, y = x + v (v white, std 0.3 of x's): least squares on the
    lagged y attenuates the pole (to about 0.9 var(x) / (var(x) + var(v)) = 0.83); the
    simulation error's fit from that head finds 0.9."""
    rng = np.random.default_rng(1)
    n = 4000
    u = np.repeat(rng.uniform(-1, 1, n // 10), 10)
    x = np.zeros(n)
    for t in range(n - 1):
        x[t + 1] = 0.9 * x[t] + 0.5 * u[t + 1]
    y = x + 0.3 * x.std() * rng.standard_normal(n)
    phi = np.column_stack([y[:-1], u[1:], np.ones(n - 1)])
    ls = np.linalg.lstsq(phi, y[1:], rcond=None)[0]
    assert ls[0] < 0.86
    shape = NarxShape(1, 1, order=1, features=0, hidden=(1,))
    start = FeatureNarx(shape, identity(), {'head': torch.from_numpy(ls[None].copy())})
    fit = refine_head(start, [(u[:, None], y[:, None])])
    a, b, c = fit.model.params['head'][0].numpy()
    assert abs(a - 0.9) < 0.01 and abs(b - 0.5) < 0.03 and abs(c) < 0.02
    assert fit.loss < fit.loss_start


def test_bad_records_and_settings_are_refused():
    shape = NarxShape(1, 1, order=2, features=0, hidden=(1,))
    model = FeatureNarx(shape, identity(), init_params(shape, 0))
    with pytest.raises(ValueError, match='at least one record'):
        refine_head(model, [])
    with pytest.raises(ValueError, match='needs more than 2'):
        refine_head(model, [(np.zeros((2, 1)), np.zeros((2, 1)))])
    with pytest.raises(ValueError, match='iterations'):
        OutputErrorConfig(iterations=0)
