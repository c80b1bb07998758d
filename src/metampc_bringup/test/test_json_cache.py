"""studies/json_cache.py: a saved object read back only when it holds every setting asked for
(a missing file, a changed value or a missing key: None), the object whole."""
import json

from metampc_bringup.studies.json_cache import cached, save


def test_read_back_only_with_the_settings_asked_for(tmp_path):
    path = str(tmp_path / 'step.json')
    assert cached(path, {'seed': 0}) is None
    value = {'seed': 0, 'config': 'a.yaml', 'rows': [1.5, float('inf')]}
    save(path, value)
    assert json.loads((tmp_path / 'step.json').read_text())['rows'] == [1.5, float('inf')]
    assert cached(path, {'seed': 0, 'config': 'a.yaml'}) == value
    assert cached(path, {}) == value
    assert cached(path, {'seed': 1}) is None
    assert cached(path, {'seed': 0, 'n_systems': 0}) is None      # a setting it lacks
