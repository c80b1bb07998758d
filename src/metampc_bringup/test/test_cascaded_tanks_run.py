"""studies/cascaded_tanks_run.py: each fitted NSSM's tracking run on the twin grouped by fit
beside the NMPC's, its series the episode's first channel, and bad options refused before
anything runs (the whole run end to end: test/test_cascaded_tanks_benchmark.py)."""
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from metampc_bringup.studies import cascaded_tanks_run
from metampc_bringup.studies.cascaded_tanks import TanksOptions

ROOT = Path(__file__).resolve().parents[3]


@dataclass
class Result:
    cost: float
    escaped: bool = False
    rejected: str = ''


def test_twin_runs_are_grouped_by_fit_beside_the_nmpc(monkeypatch):
    def fake_track(experiment, theta, x0, fitted, episodes):
        assert (theta, x0) == ([1.0], [2.0])
        for i, name in enumerate(fitted):
            k = np.arange(4.0) + i
            episodes[name] = type('Episode', (), {'y': np.stack([k, -k], 1), 'u': k[:, None],
                                                  'y_ref': k[1:, None]})
        return {name: Result(float(i)) for i, name in enumerate(fitted)}

    monkeypatch.setattr(cascaded_tanks_run, 'track_twin', fake_track)
    nmpc = {'cost': 0.5}
    fitted = {'imaml 300': None, 'maml 300': None, 'imaml 1024': None}
    rows, series = cascaded_tanks_run.twin(None, {'theta': [1.0], 'x0': [2.0]}, fitted, nmpc)
    assert rows == {'fit 300': {'nmpc': nmpc, 'imaml': {'cost': 0.0, 'escaped': False,
                                                        'rejected': ''},
                                'maml': {'cost': 1.0, 'escaped': False, 'rejected': ''}},
                    'fit 1024': {'nmpc': nmpc, 'imaml': {'cost': 2.0, 'escaped': False,
                                                         'rejected': ''}}}
    assert series['maml 300']['y'].tolist() == [1.0, 2.0, 3.0, 4.0]     # the first output
    assert series['imaml 1024']['y_ref'].tolist() == [3.0, 4.0, 5.0]


@pytest.mark.parametrize('change, message', [
    ({'seeds': (0, 1, 0)}, '--seed: each seed once, got [0, 1, 0]'),
    ({'n_systems': -1}, 'must be >= 0'),
    ({'config': str(ROOT / 'config' / 'quadruple_tank.yaml')}, 'not cascaded_tanks'),
    ({'polish': 0}, 'must be'),
])
def test_bad_options_are_refused_before_anything_runs(tmp_path, change, message):
    options = TanksOptions(out=str(tmp_path / 'o'), config=str(ROOT / 'config' /
                                                               'cascaded_tanks.yaml'))
    cascaded_tanks_run.checked(options)      # the defaults run
    with pytest.raises(cascaded_tanks_run.BadOptions, match=message.replace('[', r'\[')):
        cascaded_tanks_run.run(replace(options, **change))
    assert not (tmp_path / 'o').exists()
