"""The validation protocol on records made by known models: an exact ARX model and the
cascaded_tanks member that made the data are found and score zero; a tail shifted by 0.5 V
(fitting only the head) scores 0.5 V in simulation; bad settings are one clear error."""
from identification_records import ARX_TRUE, arx_record, TANKS, TANKS_TRUE, tanks_record
import numpy as np
import pytest

from metampc_plant.identification.arx import fit_arx
from metampc_plant.identification.validation import (arx_baseline, greybox_baseline, Protocol,
                                                     rmse)


def test_origins_lie_in_the_tail_and_bad_settings_are_refused():
    protocol = Protocol()
    origins = protocol.origins(1024)
    assert origins[0] == 767 and origins[-1] == 1013      # y[768..777] .. y[1014..1023]
    assert Protocol(validation_start=5, fit_samples=5).origins(50)[0] == 9    # t - H + 1 >= 0
    for changes, match in (({'fit_samples': 800}, r'fit_samples \(800\) <= validation_start'),
                           ({'validation_start': 1020}, r'<= 1013 \(N - T - 1\)'),
                           ({'polish': 0}, 'must be >= 1'), ({'spread': 1.0}, 'spread > 1'),
                           ({'max_order': 10}, 'exceed history 10')):
        with pytest.raises(ValueError, match=match):
            Protocol(**changes).check(1024)


def test_arx_baseline_finds_an_exact_model_of_a_linear_record():
    u = np.random.default_rng(4).uniform(-1.0, 1.0, 400)
    y = arx_record(ARX_TRUE, u, np.zeros(400))
    protocol = Protocol(fit_samples=250, validation_start=300, max_order=3)
    model, scores = arx_baseline(u, y, protocol)
    assert scores.simulation_rmse < 1e-8 and scores.prediction_rmse < 1e-8
    orders = len(model.a), len(model.b), model.nk
    refit = fit_arx(u[:250], y[:250], *orders)      # fitted on the head only
    assert np.array_equal(refit.a, model.a) and np.array_equal(refit.b, model.b)


def test_greybox_baseline_fits_the_head_and_scores_the_tail():
    u, _, y = tanks_record()
    shifted = y[:, 0] + np.where(np.arange(200) >= 150, 0.5, 0.0)
    protocol = Protocol(fit_samples=120, validation_start=150, candidates=16, polish=1,
                        spread=1.5, substeps=2)
    fit, scores = greybox_baseline(TANKS, u[:, 0], shifted, protocol, TANKS.nominal_theta,
                                   (np.zeros(5), np.full(5, np.inf)))
    assert np.allclose(fit.theta, TANKS_TRUE, rtol=1e-6) and fit.rmse < 1e-6
    assert scores.simulation_rmse == pytest.approx(0.5, abs=1e-6)
    assert 0.0 < scores.prediction_rmse < 1.0
    assert rmse(np.array([1.0, np.inf]), np.zeros(2)) == float('inf')
