"""Percentile summaries against numpy.percentile and values worked out by hand."""
import numpy as np
import pytest

from metampc_bringup.analysis.percentiles import percentiles


def test_default_points_against_numpy():
    values = np.random.default_rng(0).exponential(1e-3, size=1001)   # s
    got = percentiles(values, scale=1e3)
    ms = values * 1e3
    assert list(got) == ['p50', 'p99', 'p999', 'max']
    for name, q in (('p50', 50), ('p99', 99), ('p999', 99.9)):
        assert got[name] == round(float(np.percentile(ms, q)), 4)
    assert got['max'] == round(float(ms.max()), 4)


def test_interpolates_linearly_by_hand():
    # 0, 1, ..., 10: the q-th percentile is q / 10; p99.9 = 9.99
    got = percentiles(range(11), points=(50, 99, 99.9, 100), digits=6)
    assert got == {'p50': 5.0, 'p99': 9.9, 'p999': 9.99, 'max': 10.0}


def test_keys_points_and_rounding_as_asked():
    got = percentiles([1e-6, 2e-6, 4e-6], (50, 100), scale=1e6, digits=1, key='tick_{}_us')
    assert got == {'tick_p50_us': 2.0, 'tick_max_us': 4.0}
    assert percentiles([0.123456], (99,), digits=2) == {'p99': pytest.approx(0.12, abs=0)}


def test_empty_is_empty():
    assert percentiles([]) == {}
