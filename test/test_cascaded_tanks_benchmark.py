"""scripts/cascaded_tanks_benchmark.py: the NSSM's free-run simulation against a recursion
written out by hand, the record's sample pairing, the summary over seeds against figures
worked out by hand, and the script end to end on a tiny budget and a short twin run (resumed
from its cache), with one error line and exit status 2 for bad input."""
import json
from pathlib import Path
import runpy

import numpy as np
import pytest
import torch

from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_plant.families.cascaded_tanks import FIT_THETA, FIT_X0

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = runpy.run_path(str(ROOT / 'scripts' / 'cascaded_tanks_benchmark.py'))
TINY = ['--meta-iterations', '1', '--n-systems', '5', '--max-steps', '1', '--candidates', '2',
        '--polish', '1', '--substeps', '1']


def test_trajectory_pairs_each_input_with_the_next_level():
    u, y = np.arange(10.0), 100 + np.arange(10.0)
    t = SCRIPT['trajectory'](u, y, 2, 6)
    assert t.steps.tolist() == [2, 3, 4]
    assert t.u[:, 0].tolist() == [2, 3, 4] and t.y[:, 0].tolist() == [103, 104, 105]


def test_free_run_simulation_is_the_latent_recursion_from_the_encoded_state():
    # One latent state, the encoder's output fixed by its last bias (z = 0.7 whatever it
    # reads), identity normalisation: y[H+1+j] = C z_j+1 with z_{j+1} = a z_j + b u[H+j].
    cfg = NssmConfig(n_u=1, n_y=1, n_z=1, history=3, hidden=(4,), loss_horizon=2,
                     stable_latent=False)
    model = Nssm(cfg, dtype=torch.float64)
    params = {k: torch.zeros_like(v) for k, v in model.params().items()}
    params['encoder.1.bias'] = torch.tensor([0.7], dtype=torch.float64)
    a, b, c = 0.9, 0.5, 2.0
    params.update(A=torch.tensor([[a]], dtype=torch.float64),
                  B=torch.tensor([[b]], dtype=torch.float64),
                  C=torch.tensor([[c]], dtype=torch.float64))
    rng = np.random.default_rng(0)
    u, y = rng.uniform(0, 5, 12), rng.uniform(0, 5, 12)
    sim = SCRIPT['simulate_nssm'](model, params, u, y)
    assert np.all(np.isnan(sim[:4]))
    z, expected = 0.7, []
    for k in range(3, 11):
        z = a * z + b * u[k]
        expected.append(c * z)
    np.testing.assert_allclose(sim[4:], expected, rtol=1e-12)


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


def _report(seed: int, sim: float, cost: float, nmpc: dict) -> dict:
    result = {'cost': cost, 'escaped': False, 'rejected': '', 'offsets': [0.1]}
    return {'seed': seed, 'rows': [{'fit': 300, 'model': 'imaml', 'test': {
        'simulation_rmse': sim, 'prediction_rmse': sim / 2}}],
        'twin': {'fit 300': {'nmpc': nmpc, 'imaml': result}}}


def test_summary_over_seeds():
    nmpc = {'cost': 2.0, 'escaped': False, 'rejected': '', 'offsets': [0.01]}
    result = SCRIPT['summary']([_report(0, 1.0, 3.0, nmpc), _report(1, 3.0, 5.0, nmpc),
                                _report(2, 1.5, 9.0, nmpc)], nmpc)
    sim = result['test'][0]['simulation_rmse']
    assert (sim['median'], sim['min'], sim['max']) == (1.5, 1.0, 3.0)
    twin = result['twin']['fit 300']['imaml']
    assert twin['ratios'] == {0: 1.5, 1: 2.5, 2: 4.5}
    assert (twin['median'], twin['worst'], twin['escapes']) == (2.5, 4.5, 0)
    assert '| estimation 0..299 | imaml | 1.5, 2.5, 4.5 | 2.5 | 4.5 | 0 | 0 | 0.100 |' in \
        SCRIPT['twin_table'](result)
    assert '| 1.5000 (1.0000..3.0000) | 0.7500 (0.5000..1.5000) |' in SCRIPT['table'](result)


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

    monkeypatch.setitem(SCRIPT['greybox'].__globals__, 'fit_greybox_head', fake_fit)
    args = SimpleNamespace(out=str(tmp_path))
    protocol = SimpleNamespace(candidates=2, polish=1, substeps=1)
    with pytest.raises(SCRIPT['OutOfRange'], match="left the family's parameter range"):
        SCRIPT['greybox'](args, family, None, None, 300, protocol)
    assert not (tmp_path / 'greybox_300.json').exists()
    (tmp_path / 'greybox_300.json').write_text(json.dumps(
        {'n': 300, 'candidates': 2, 'polish': 1, 'substeps': 1, 'theta': (lo * 0.5).tolist()}))
    got = SCRIPT['greybox'](args, family, None, None, 300, protocol)
    assert fits == [300, 300] and got['theta'] == lo.tolist()
