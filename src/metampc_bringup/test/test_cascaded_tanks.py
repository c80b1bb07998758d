"""studies/cascaded_tanks.py: the choice of the adaptation step size and steps against the
least held-out loss read off by hand (a step size whose loss turned non-finite left out), the
test-record scores against RMSEs written out, and a grey-box fit out of the family's range
refused and not cached."""
import json
from types import SimpleNamespace

import numpy as np
import pytest

from metampc_bringup.studies import cascaded_tanks


def test_the_step_size_and_steps_of_least_held_out_loss_are_chosen(monkeypatch):
    curves = {0.03: [5.0, 4.0, 3.0], 0.1: [5.0, 2.0, 2.5], 0.3: None, 1.0: [5.0, np.nan, 2.2]}

    def fake(model, init, method, train, held, lr, steps, settings):
        assert steps == 2
        if curves[lr] is None:
            raise ValueError('non-finite loss')
        return SimpleNamespace(result=SimpleNamespace(heldout_loss=np.array(curves[lr])))

    monkeypatch.setattr(cascaded_tanks, 'run_adaptation', fake)
    chosen = cascaded_tanks.choose_adaptation(None, None, 'imaml', None, None, 2, None)
    assert chosen == {'lr': 0.1, 'steps': 1, 'heldout_loss': 2.0}


def test_scores_are_the_simulation_and_t_step_rmse():
    y = np.arange(10.0)
    y_sim = y + np.array([9.0] * 3 + [1.0, -1.0] * 3 + [1.0])     # off by 1 from sample 3
    origins = np.array([2, 5])
    predicted = np.array([[3.0, 4.0], [8.0, 9.0]])     # y[3..4] exact, y[6..7] off by 2
    got = cascaded_tanks.scores(y, y_sim, predicted, origins, 2, 3)
    assert got['simulation_rmse'] == pytest.approx(1.0)
    assert got['prediction_rmse'] == pytest.approx(np.sqrt(2.0))


def test_a_fit_out_of_the_family_range_is_refused_and_not_cached(tmp_path, monkeypatch):
    """Issue 52 item 6: a grey-box fit that leaves the family's parameter range is refused in
    one line and not cached; a cached one out of the range is fitted again (fails on the
    old code: cached, then the twin's traceback, and the same command failing again)."""
    from types import SimpleNamespace
    from metampc_plant.registry import get_family
    family = get_family('cascaded_tanks')
    lo = np.array([c.support[0] for c in family.theta])
    fits = []

    def fake_fit(family, u, y, n, protocol, guess, bounds):
        fits.append(n)
        theta = lo * (0.5 if len(fits) == 1 else 1.0)       # out of range, then in range
        return SimpleNamespace(theta=theta, x0=np.zeros(family.n_x), rmse=0.1)

    monkeypatch.setattr(cascaded_tanks, 'fit_greybox_head', fake_fit)
    args = SimpleNamespace(out=str(tmp_path))
    protocol = SimpleNamespace(candidates=2, polish=1, substeps=1)
    with pytest.raises(cascaded_tanks.OutOfRange, match="left the family's parameter range"):
        cascaded_tanks.greybox(args, family, None, None, 300, protocol)
    assert not (tmp_path / 'greybox_300.json').exists()
    (tmp_path / 'greybox_300.json').write_text(json.dumps(
        {'n': 300, 'candidates': 2, 'polish': 1, 'substeps': 1, 'theta': (lo * 0.5).tolist()}))
    got = cascaded_tanks.greybox(args, family, None, None, 300, protocol)
    assert fits == [300, 300] and got['theta'] == lo.tolist()
