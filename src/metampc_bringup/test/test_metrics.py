"""Metric functions on plain arrays, against values worked out by hand."""
import math

from metampc_bringup.metrics import (bound_violations, episodes, percentile_summary,
                                     reference_pairs, tick_accounting, tracking_metrics)
import numpy as np
import pytest


def test_episodes_restart_where_the_step_decreases():
    assert episodes([0, 1, 2, 0, 1, 5, 6, 2]).tolist() == [0, 0, 0, 1, 1, 1, 1, 2]
    assert episodes([]).tolist() == []


def test_reference_of_step_k_pairs_with_output_k_plus_1_in_the_same_episode():
    outputs = [0, 1, 2, 3, 0, 1, 2]      # a reset after step 3
    statuses = [0, 1, 3, 0, 1, 2]        # step 2 of episode 0 unanswered; 3 and 2 have no k+1
    out_idx, status_idx = reference_pairs(outputs, statuses)
    assert list(zip(out_idx.tolist(), status_idx.tolist())) == [(1, 0), (2, 1), (5, 3), (6, 4)]


def test_tracking_metrics_by_hand():
    y = np.array([[1.0, 5.0], [2.0, 5.0], [0.0, 5.0], [9.0, 9.0]])
    r = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [np.nan, 0.0]])   # last row: no reference
    m = tracking_metrics(y, r, [0])
    assert m['samples'] == 3
    assert m['cost'] == 1.0 + 4.0 + 1.0
    assert m['rmse'] == pytest.approx(math.sqrt(6.0 / 3), rel=1e-15)
    assert m['per_output']['0'] == {'rmse': m['rmse'], 'sse': 6.0, 'max_abs_error': 2.0}
    both = tracking_metrics(y[:3], r[:3], [0, 1])
    assert both['cost'] == 6.0 + 75.0
    assert both['rmse'] == pytest.approx(math.sqrt(81.0 / 6), rel=1e-15)
    assert tracking_metrics(np.zeros((0, 2)), np.zeros((0, 2)), [0])['rmse'] is None


def test_percentiles_bounds_and_ticks():
    s = percentile_summary([4.0, 1.0, 3.0, 2.0])
    assert s == {'count': 4, 'mean': 2.5, 'p50': 2.5, 'p99': pytest.approx(3.97), 'max': 4.0}
    assert percentile_summary([])['p50'] is None
    u = np.array([[0.5], [1.0 + 1e-12], [1.25], [-1.5]])
    assert bound_violations(u, -1.0, 1.0) == {'u_min': [-1.0], 'u_max': [1.0], 'violations': 2,
                                              'max_excess': 0.5}
    # Bounds per input: the second input of the third sample is 0.5 above its own bound.
    two = np.array([[0.5, 9.0], [0.0, 10.0], [0.2, 10.5]])
    assert bound_violations(two, [0.0, 0.0], [1.0, 10.0]) == {
        'u_min': [0.0, 0.0], 'u_max': [1.0, 10.0], 'violations': 1, 'max_excess': 0.5}
    # Steps 0-1 unanswered (start-up), then step 4 and step 1 of episode 1 missed; the last
    # output (episode 1, step 3) is outside the window.
    outputs = [0, 1, 2, 3, 4, 5, 0, 1, 2, 3]
    inputs = [2, 3, 5, 0, 2]
    assert tick_accounting(outputs, inputs) == {'considered': 7, 'answered': 5, 'missed': 2}
    assert tick_accounting(outputs, []) == {'considered': 0, 'answered': 0, 'missed': 0}
