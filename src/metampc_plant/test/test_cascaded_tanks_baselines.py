"""scripts/cascaded_tanks_baselines.py as a user runs it: one JSON line with the figures the
protocol computes, a table, --help, and one error line with exit status 2 for bad settings."""
import json
from pathlib import Path
import runpy

import pytest

from metampc_plant.cascaded_tanks_data import load_cascaded_tanks
from metampc_plant.identification.validation import arx_baseline, Protocol

ROOT = Path(__file__).resolve().parents[3]
# Small and quick (the documented figures take minutes): 100 fitted samples, 14 T-step
# origins, 4 grey-box candidates, 1 search, RK4 at one step a sample.
FAST = ['--fit-samples', '100', '--validation-start', '1000', '--candidates', '4', '--polish',
        '1', '--substeps', '1', '--max-order', '2', '--max-delay', '0']


def _main():
    return runpy.run_path(str(ROOT / 'scripts' / 'cascaded_tanks_baselines.py'))['main']


def test_one_json_line_of_the_protocols_figures(capsys):
    assert _main()(FAST) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1
    report = json.loads(lines[0])
    assert (report['fit_samples'], report['validation'], report['horizon']) == (100, [1000, 1024],
                                                                                10)
    data = load_cascaded_tanks()
    model, scores = arx_baseline(data.u_est, data.y_est,
                                 Protocol(fit_samples=100, validation_start=1000, max_order=2,
                                          max_delay=0))
    arx = report['arx']
    assert (arx['na'], arx['nb'], arx['nk']) == (len(model.a), len(model.b), 0)
    assert arx['simulation_rmse'] == round(scores.simulation_rmse, 4)
    assert arx['prediction_rmse'] == round(scores.prediction_rmse, 4)
    grey = report['greybox']
    assert len(grey['theta']) == 5 and len(grey['x0']) == 2 and min(grey['theta']) >= 0.0
    assert all(0.0 < grey[k] < 10.0 for k in ('fit_rmse', 'simulation_rmse', 'prediction_rmse'))


def test_table_help_and_bad_settings(capsys):
    main = _main()
    assert main(FAST + ['--table']) == 0
    table = capsys.readouterr().out
    assert 'scored on 1000..1023' in table and 'grey-box' in table and 'ARX(' in table
    with pytest.raises(SystemExit) as done:
        main(['--help'])
    assert done.value.code == 0 and '--fit-samples' in capsys.readouterr().out
    assert main(['--fit-samples', '900']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ['cascaded_tanks_baselines: need 20 <= fit_samples (900) <= validation_start '
                   '(768) <= 1013 (N - T - 1)']
