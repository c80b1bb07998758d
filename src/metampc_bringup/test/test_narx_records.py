"""analysis/narx_records.py: the feature NARX's free run and T-step prediction on a record,
checked against identification.arx's simulation and prediction of the same ARX and against
FeatureNarx.step (numpy) fed back by hand."""
import numpy as np
import pytest

from metampc_bringup.analysis.narx_records import free_run, predict
from metampc_learner.narx_learning import arx_model
from metampc_model.feature_narx import FeatureNarx, init_params, NarxShape
from metampc_model.normalisation import Normalisation
from metampc_plant.identification.arx import fit_arx, predict_arx, simulate_arx

ORDER = 3


def record(n: int = 120):
    """A stable nonlinear SISO record (u[k] produced y[k]), physical units off zero."""
    rng = np.random.default_rng(4)
    u = 2.0 + rng.uniform(-1.0, 1.0, n)
    y = np.full(n, 5.0)
    for k in range(2, n):
        y[k] = 1.5 + 0.6 * y[k - 1] + 0.1 * y[k - 2] + 0.4 * u[k] + 0.2 * np.sin(y[k - 1]) \
            + 0.05 * rng.standard_normal()
    return u[:, None], y[:, None]


def meta_model() -> FeatureNarx:
    """A feature NARX of random features, its normalisation not the data's."""
    shape = NarxShape(1, 1, ORDER, 8, (16,))
    norm = Normalisation(np.array([1.5]), np.array([0.7]), np.array([4.0]), np.array([2.0]))
    return FeatureNarx(shape, norm, init_params(shape, 0))


def test_free_run_and_prediction_of_an_arx_head_are_identification_arx():
    u, y = record()
    model = arx_model(meta_model(), [(u, y)])
    arx = fit_arx(u[:, 0], y[:, 0], ORDER, ORDER, 0)       # the same one-step equations
    # Two least-squares solves (normal equations in normalised units, lstsq in physical ones):
    # equal to 2e-8 V; a shifted lag or input errs by tenths of a volt.
    np.testing.assert_allclose(free_run(model, u, y)[:, 0], simulate_arx(arx, u[:, 0], y[:, 0]),
                               rtol=0, atol=1e-6)
    origins = np.array([ORDER - 1, 40, len(y) - 11])
    np.testing.assert_allclose(predict(model, u, y, origins, 10)[..., 0],
                               predict_arx(arx, u[:, 0], y[:, 0], origins, 10), rtol=0,
                               atol=1e-6)


def test_free_run_feeds_back_its_own_outputs_through_the_features():
    u, y = record()
    model = meta_model()
    model.params['head'][:] = 0.1                          # every column, features included
    model.params['head'][0, 0] = 0.5
    expected = list(y[:ORDER])
    for k in range(ORDER, len(y)):
        s = model.state(u[k - ORDER + 1:k], np.array(expected[k - ORDER:k]))
        expected.append(model.step(s, u[k]))
    altered = y.copy()
    altered[ORDER:] += 100.0                                # never read by the free run
    np.testing.assert_allclose(free_run(model, u, altered), np.array(expected), rtol=1e-12,
                               atol=1e-12)


def test_records_too_short_and_origins_out_of_range_are_refused():
    u, y = record(20)
    model = meta_model()
    with pytest.raises(ValueError, match='more than 3 samples'):
        free_run(model, u[:ORDER], y[:ORDER])
    for origins in ([ORDER - 2], [len(y) - 10], []):
        with pytest.raises(ValueError, match='origins'):
            predict(model, u, y, origins, 10)
