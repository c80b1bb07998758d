"""studies/cascaded_tanks_narx.py: the feature NARX's free run over a record in the tanks'
pairing (u[k] acts first on y[k+1]) against identification.arx's simulation of the same ARX on
the record shifted by hand, and the rows read back from the cache only for the same settings."""
import json
from types import SimpleNamespace

import numpy as np
import pytest

from metampc_bringup.studies import cascaded_tanks_narx
from metampc_learner.narx_learning import arx_model
from metampc_model.feature_narx import FeatureNarx, init_params, NarxShape
from metampc_model.normalisation import Normalisation
from metampc_plant.identification.arx import fit_arx, simulate_arx


def test_free_run_of_an_arx_head_is_the_arx_simulation_of_the_shifted_record():
    rng = np.random.default_rng(1)
    u = 2.0 + rng.uniform(-1.0, 1.0, 80)
    y = np.full(80, 5.0)
    for k in range(1, 80):       # u[k-1] acts on y[k]
        y[k] = 1.0 + 0.7 * y[k - 1] + 0.5 * u[k - 1] + 0.05 * rng.standard_normal()
    shape = NarxShape(1, 1, 2, 8, (16,))
    norm = Normalisation(np.array([2.0]), np.array([0.6]), np.array([5.0]), np.array([1.0]))
    u_n, y_n = cascaded_tanks_narx.narx_record(u, y, 0, 80)
    np.testing.assert_array_equal(u_n[:, 0], u[:-1])
    np.testing.assert_array_equal(y_n[:, 0], y[1:])
    model = arx_model(FeatureNarx(shape, norm, init_params(shape, 0)), [(u_n, y_n)])
    arx = fit_arx(u[:-1], y[1:], 2, 2, 0)
    sim = cascaded_tanks_narx.narx_simulation(model, u, y)
    assert sim.shape == (80,) and np.isnan(sim[0])
    np.testing.assert_allclose(sim[1:], simulate_arx(arx, u[:-1], y[1:]), rtol=0, atol=1e-6)


def test_rows_are_read_back_for_the_same_settings_only(tmp_path, monkeypatch):
    options = SimpleNamespace(out=str(tmp_path), config='c.yaml', meta_iterations=1,
                              n_systems=5)
    (tmp_path / 'seed_3').mkdir()
    wanted = {'seed': 3, 'config': 'c.yaml', 'orders': list(cascaded_tanks_narx.NARX_ORDERS),
              'narx': repr(cascaded_tanks_narx.NARX), 'meta_iterations': 1, 'n_systems': 5}
    (tmp_path / 'seed_3' / 'narx.json').write_text(json.dumps({**wanted, 'rows': ['cached']}))

    def refit(options, seed):
        raise RuntimeError('fitted again')

    monkeypatch.setattr(cascaded_tanks_narx, 'narx_metas', refit)
    assert cascaded_tanks_narx.narx_rows(options, None, 3, None) == ['cached']
    options.n_systems = 6
    with pytest.raises(RuntimeError, match='fitted again'):
        cascaded_tanks_narx.narx_rows(options, None, 3, None)
