"""scripts/cascaded_tanks_benchmark.py: the script end to end on a tiny budget and a short twin
run (resumed from its cache), with one error line and exit status 2 for bad input. Its parts
are tested in src/metampc_bringup/test/ (test_cascaded_tanks*.py, test_nssm_records.py,
test_json_cache.py)."""
import json
from pathlib import Path
import runpy

import numpy as np
import pytest

from metampc_plant.families.cascaded_tanks import FIT_THETA, FIT_X0

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = runpy.run_path(str(ROOT / 'scripts' / 'cascaded_tanks_benchmark.py'))
TINY = ['--meta-iterations', '1', '--n-systems', '5', '--max-steps', '1', '--candidates', '2',
        '--polish', '1', '--substeps', '1']


def _cache_greybox(out: Path):
    # The documented fit stands in for the grey-box searches (minutes): the script reads it.
    out.mkdir()
    for n in (300, 1024):
        (out / f'greybox_{n}.json').write_text(json.dumps({
            'n': n, 'candidates': 2, 'polish': 1, 'substeps': 1, 'theta': list(FIT_THETA),
            'x0': list(FIT_X0), 'fit_rmse': 0.0, 'seconds': 0.0}))


def _short_config(tmp_path: Path) -> str:
    # The twin's tracking run cut to 10 samples of the first set-point, a 5-sample horizon.
    text = (ROOT / 'config' / 'cascaded_tanks.yaml').read_text()
    text = text.replace('track_duration: 3200.0', 'track_duration: 40.0')
    text = text.replace('  horizon: 20 ', '  horizon: 5 ').replace('nmpc_tail: 20', 'nmpc_tail: 5')
    path = tmp_path / 'short.yaml'
    path.write_text(text)
    return str(path)


def test_tiny_budget_end_to_end_and_resumed(tmp_path, capsys):
    out = tmp_path / 'cts'
    _cache_greybox(out)
    figures = ['--figure', str(tmp_path / 'f.png'), '--twin-figure', str(tmp_path / 't.png')]
    args = ['--out', str(out), '--config', _short_config(tmp_path), *TINY]
    assert SCRIPT['main']([*args, *figures]) == 0
    captured = capsys.readouterr()
    assert 'imaml: meta-training, 1 outer steps' in captured.err
    # header, 10 rows, the feature NARX and its ARX(p) at both fits (4), 3 published; a blank
    # line; header, 6 rows, the NMPC
    assert captured.out.count('\n') == 2 + 10 + 4 + 3 + 1 + 2 + 6 + 1
    assert captured.out.count('feature NARX') >= 2
    report = json.loads((out / 'seed_0' / 'benchmark.json').read_text())
    assert [r['fit'] for r in report['rows']] == [300] * 5 + [1024] * 5
    grey = [r for r in report['rows'] if r['model'] == 'grey-box']
    assert grey[0]['test'] == grey[1]['test']     # the same cached fit
    # The family's fit run from x(0) over the test record: the documented level of error.
    assert 0.2 < grey[0]['test_all_samples'] < 1.0
    nmpc = json.loads((out / 'twin_nmpc.json').read_text())
    assert nmpc['theta'] == list(FIT_THETA) and len(nmpc['series']['y']) == 11
    for fit in ('fit 300', 'fit 1024'):
        twin = report['twin'][fit]
        assert sorted(twin) == ['imaml', 'maml', 'nmpc', 'supervised']
        assert all(not r['rejected'] and np.isfinite(r['cost']) for r in twin.values())
    assert all((tmp_path / name).stat().st_size > 1000 for name in ('f.png', 't.png'))
    assert SCRIPT['main'](args) == 0
    resumed = capsys.readouterr()
    assert 'seed 0: cached' in resumed.err and 'twin: the NMPC' not in resumed.err
    assert resumed.out == captured.out


@pytest.mark.parametrize('args, message', [
    (['--max-steps', '-1'], 'must be >= 0'),
    (['--config', 'config/quadruple_tank.yaml'], 'not cascaded_tanks'),
    (['--config', '/nonexistent.yaml'], 'cannot read config'),
    (['--seed', '1', '1'], 'each seed once'),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, message):
    assert SCRIPT['main'](['--out', str(tmp_path / 'o'), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count('\n') == 1


def test_out_that_is_a_file_is_refused(tmp_path, capsys):
    path = tmp_path / 'file'
    path.write_text('')
    assert SCRIPT['main'](['--out', str(path)]) == 2
    assert 'is not a folder' in capsys.readouterr().err
