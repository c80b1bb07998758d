"""ARX fit, simulation and T-step prediction against known linear systems: exact recovery of
the coefficients from noise-free data, consistency under equation noise, and a first-order
model's T-step prediction against its closed form."""
from identification_records import ARX_TRUE as TRUE, arx_record as generate
import numpy as np
import pytest

from metampc_plant.identification.arx import Arx, fit_arx, predict_arx, simulate_arx


def test_noise_free_data_give_the_coefficients_and_the_simulation_back():
    u = np.random.default_rng(0).uniform(-1.0, 1.0, 400)
    y = generate(TRUE, u, np.zeros(400))
    fit = fit_arx(u, y, 2, 2, 1)
    assert np.allclose(fit.a, TRUE.a, atol=1e-10) and np.allclose(fit.b, TRUE.b, atol=1e-10)
    assert fit.c == pytest.approx(TRUE.c, abs=1e-10) and fit.nk == 1 and fit.lag == 2
    assert np.allclose(simulate_arx(fit, u, y), y, atol=1e-9)


def test_equation_noise_estimates_are_consistent():
    rng = np.random.default_rng(1)
    u = rng.uniform(-1.0, 1.0, 20000)
    y = generate(TRUE, u, 0.05 * rng.standard_normal(20000))
    fit = fit_arx(u, y, 2, 2, 1)
    # white equation noise: least squares is consistent; std of each estimate ~ 1e-3 here
    assert np.allclose(fit.a, TRUE.a, atol=0.01) and np.allclose(fit.b, TRUE.b, atol=0.01)
    assert fit.c == pytest.approx(TRUE.c, abs=0.02)


def test_t_step_prediction_of_a_first_order_model_is_its_closed_form():
    # y[k] = a y[k-1] + b u[k-1] + c: y[t+T] = a^T y[t] + sum_j a^j (b u[t+T-1-j] + c)
    a, b, c, horizon = 0.8, 0.5, 0.1, 6
    model = Arx(a=np.array([a]), b=np.array([b]), nk=1, c=c)
    rng = np.random.default_rng(2)
    u, y = rng.uniform(-1.0, 1.0, 50), rng.uniform(-1.0, 1.0, 50)   # y: any measured record
    origins = np.array([0, 7, 43])
    predicted = predict_arx(model, u, y, origins, horizon)
    for row, t in zip(predicted, origins):
        expected = [a ** s * y[t] + sum(a ** j * (b * u[t + s - 1 - j] + c) for j in range(s))
                    for s in range(1, horizon + 1)]
        assert np.allclose(row, expected, atol=1e-12)


def test_bad_orders_short_records_and_origins_are_refused():
    u = y = np.zeros(10)
    with pytest.raises(ValueError, match='na >= 0, nb >= 1'):
        fit_arx(u, y, 1, 0, 1)
    with pytest.raises(ValueError, match='needs more than'):
        fit_arx(u, y, 4, 4, 1)
    with pytest.raises(ValueError, match='one shape'):
        fit_arx(u, y[:5], 1, 1, 1)
    with pytest.raises(ValueError, match=r'T-step origins need 1 <= t <= 7'):
        predict_arx(TRUE, u, y, [0], 2)
