"""drift_report's metrics on hand-made signals: the moving cost against a loop, the time to
recover by its definition, and the before/after costs against the NMPC's."""
import math

import numpy as np

from metampc_bringup.drift_report import (moving_cost, recovery_time, run_metrics,
                                          RunSignals, squared_errors)


def test_moving_cost_is_the_trailing_mean():
    e2 = np.array([1.0, 2.0, np.nan, 4.0, 5.0, 6.0])
    got = moving_cost(e2, 3)
    want = []
    for k in range(len(e2)):
        window = [v for v in e2[max(0, k - 2):k + 1] if not math.isnan(v)]
        want.append(sum(window) / len(window))
    assert np.allclose(got, want)


def test_recovery_time_by_its_definition():
    t = np.arange(0, 10.0, 1.0)
    ratio = np.array([1.0, 1.0, 1.0, 3.0, 2.0, 1.3, 1.1, 1.0, 2.0, 1.0])
    assert recovery_time(ratio, t, 2.0) == 4.0      # over at 3 s, back within at 6 s
    assert recovery_time(np.ones(10), t, 2.0) == 0.0    # never exceeded
    assert recovery_time(np.r_[np.ones(3), np.full(7, 5.0)], t, 2.0) is None  # never back


def signals(y, ref, version=None, requests=()):
    n = len(y)
    steps = np.arange(n - 1)
    return RunSignals(t=0.1 * np.arange(n), y=np.asarray(y, float).reshape(n, 1),
                      theta=np.zeros((n, 1)), step=steps,
                      model_version=np.asarray(version if version is not None
                                               else np.ones(n - 1), dtype=np.int64),
                      error_t=np.ones(n - 1), change_t=np.zeros(n - 1),
                      request=np.isin(steps, requests),
                      trigger=['triggered' if k in requests else '' for k in steps],
                      ref=np.asarray(ref, float).reshape(n - 1, 1), compute=[0.2])


def test_run_metrics_against_hand_computed_costs():
    """Reference 0; the method's error is 0.1 before t = 2 s, 0.3 after; the NMPC's 0.1
    throughout: cost ratios 1 and 9; one request at step 25 and its swap at 35."""
    n = 61
    t_out = 0.1 * np.arange(n)
    y = np.where(t_out <= 2.0 + 1e-9, 0.1, 0.3)
    version = np.where(np.arange(n - 1) >= 35, 2, 1)
    sig = signals(y, np.zeros(n - 1), version, requests=(25,))
    nmpc = signals(np.full(n, 0.1), np.zeros(n - 1))
    e2 = squared_errors(sig, [0])
    assert np.allclose(e2, y[1:] ** 2)
    m = run_metrics(sig, nmpc, 2.0, [0])
    assert math.isclose(m['ratio_before'], 1.0) and math.isclose(m['ratio_after'], 9.0)
    assert m['requests'] == [[25, 'triggered']] and m['swaps'] == [35]
    assert m['adaptations'] == 1 and m['compute_s'] == [0.2]
    assert m['recovery_s'] is None      # 9x the NMPC's to the end
    constant = run_metrics(sig, None, None, [0])
    assert 'ratio_after' not in constant and constant['adaptations'] == 1
