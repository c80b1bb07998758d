"""analysis/cascaded_tanks_report.py: the summary over seeds and its two tables against figures
worked out by hand, one seed's figure printed alone, and the figures drawn."""
import numpy as np

from metampc_bringup.analysis.cascaded_tanks_report import figure, spread, summary, table, \
    twin_figure, twin_table


def _report(seed: int, sim: float, cost: float, nmpc: dict) -> dict:
    result = {'cost': cost, 'escaped': False, 'rejected': '', 'offsets': [0.1]}
    return {'seed': seed, 'rows': [{'fit': 300, 'model': 'imaml', 'test': {
        'simulation_rmse': sim, 'prediction_rmse': sim / 2}}],
        'twin': {'fit 300': {'nmpc': nmpc, 'imaml': result}}}


def test_summary_over_seeds():
    nmpc = {'cost': 2.0, 'escaped': False, 'rejected': '', 'offsets': [0.01]}
    result = summary([_report(0, 1.0, 3.0, nmpc), _report(1, 3.0, 5.0, nmpc),
                      _report(2, 1.5, 9.0, nmpc)], nmpc)
    sim = result['test'][0]['simulation_rmse']
    assert (sim['median'], sim['min'], sim['max']) == (1.5, 1.0, 3.0)
    twin = result['twin']['fit 300']['imaml']
    assert twin['ratios'] == {0: 1.5, 1: 2.5, 2: 4.5}
    assert (twin['median'], twin['worst'], twin['escapes']) == (2.5, 4.5, 0)
    assert '| estimation 0..299 | imaml | 1.5, 2.5, 4.5 | 2.5 | 4.5 | 0 | 0 | 0.100 |' in \
        twin_table(result)
    assert '| 1.5000 (1.0000..3.0000) | 0.7500 (0.5000..1.5000) |' in table(result)


def test_one_seed_prints_its_value_alone():
    assert spread({'median': 0.5, 'min': 0.5, 'max': 0.5}) == '0.5000'
    assert spread({'median': 0.5, 'min': 0.25, 'max': 1.0}) == '0.5000 (0.2500..1.0000)'


def test_figures_draw_every_fit(tmp_path):
    t = np.linspace(0.0, 1.0, 11)
    sims = {f'test {m} {n}': t for n in (3, 5) for m in ('imaml', 'supervised', 'ARX',
                                                         'grey-box')}
    figure(str(tmp_path / 'f.png'), t, sims, 4.0, (3, 5), ('imaml',))
    runs = {f'twin {m} {n} {p}': t for n in (3, 5) for m in ('imaml', 'supervised')
            for p in ('y', 'u')}
    twin_figure(str(tmp_path / 't.png'), 0, runs, {'y': t, 'u': t, 'y_ref': t[1:]}, 4.0,
                (3, 5), ('imaml',))
    assert all((tmp_path / name).stat().st_size > 1000 for name in ('f.png', 't.png'))
