"""drift_report's metrics on hand-made signals: the moving cost against a loop, the time to
recover by its definition, and the before/after costs against the NMPC's."""
import math

import numpy as np
import pytest

from types import SimpleNamespace

from metampc_bringup.analysis.drift_report import (drift_experiment_report, MOVING_WINDOW_S,
                                                   moving_cost, RECOVERY_FACTOR, recovery_time,
                                                   refusals, run_metrics, RunSignals,
                                                   squared_errors)


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
                      ref=np.asarray(ref, float).reshape(n - 1, 1), compute=[0.2],
                      events=[()] * (n - 1))


def event(outcome, cause='check', reason=''):
    """A recorded model event (metampc_msgs/ModelEvent's fields read here)."""
    return SimpleNamespace(outcome=outcome, cause=cause, reason=reason)


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
    m = run_metrics(sig, nmpc, 2.0, [0], 0.1)
    assert math.isclose(m['ratio_before'], 1.0) and math.isclose(m['ratio_after'], 9.0)
    assert m['requests'] == [[25, 'triggered']] and m['swaps'] == [35]
    assert m['adaptations'] == 1 and m['compute_s'] == [0.2]
    assert m['recovery_s'] is None      # 9x the NMPC's to the end
    constant = run_metrics(sig, None, None, [0], 0.1)
    assert 'ratio_after' not in constant and constant['adaptations'] == 1


@pytest.mark.parametrize('dt, expected', [(0.1, 5.9), (0.25, 6.0)])
def test_recovery_uses_a_five_second_window_whatever_the_sample_time(dt, expected):
    """Pins the recovery window in seconds (MOVING_WINDOW_S = 5 s, docs: the 5-s moving cost)
    on a run that does recover: the NMPC's squared error is 0.01 throughout, the method's 0.09
    for the first second after t_c = 2 s and 0.01 again after. The independent answer is a loop
    over output times, the moving cost at t the mean over outputs in (t - 5 s, t]: the ratio
    is back within 1.2x once at most (dt = 0.1 s) one / (dt = 0.25 s) no burst sample is left
    in the window, at t = 7.9 s / 8.0 s. A 5-sample window would give 1.5 s / 2.25 s."""
    n = int(round(12.0 / dt)) + 1
    t_out = dt * np.arange(n)
    burst = (t_out > 2.0 + 1e-9) & (t_out <= 3.0 + 1e-9)
    y = np.where(burst, 0.3, 0.1)

    def run(values):
        return RunSignals(t=t_out, y=values.reshape(n, 1), theta=np.zeros((n, 1)),
                          step=np.arange(n - 1), model_version=np.ones(n - 1, dtype=np.int64),
                          error_t=np.ones(n - 1), change_t=np.zeros(n - 1),
                          request=np.zeros(n - 1, dtype=bool), trigger=[''] * (n - 1),
                          ref=np.zeros((n - 1, 1)), compute=[])

    m = run_metrics(run(y), run(np.full(n, 0.1)), 2.0, [0], dt)
    e2, ref = y[1:] ** 2, np.full(n - 1, 0.01)
    times = t_out[1:]
    by_hand = None
    exceeded = False
    for j, tj in enumerate(times):
        inside = (times > tj - MOVING_WINDOW_S + 1e-9) & (times <= tj + 1e-9)
        ratio = e2[inside].mean() / ref[inside].mean()
        if tj > 2.0 + 1e-9:
            exceeded = exceeded or ratio > RECOVERY_FACTOR
            if exceeded and ratio <= RECOVERY_FACTOR:
                by_hand = tj - 2.0
                break
    assert MOVING_WINDOW_S == 5.0 and by_hand == pytest.approx(expected)
    assert m['recovery_s'] == pytest.approx(expected)


def test_identical_runs_started_at_different_stamps_get_identical_metrics():
    """Two runs with the same outputs, cut out of a recording at starts 90.3 s and 210.5 s (seed
    0 of the drift run in docs/adaptation.md): their header stamps less the start give sample
    times 0.1 + 9e-15 and 0.1 - 6e-15, which put the output at t_change = 30 s on opposite
    sides of the change, so `none` and a `triggered` run that never asked differed by 5 %
    before the change (cost_before 0.0320 against 0.0336). The split is by the run's dt, so
    both equal the hand-computed split (the outputs up to and at 30 s before, the rest after)."""
    n = 601
    y = np.linspace(0.0, 1.0, n) ** 2
    got = []
    for start in (90.3, 210.5):
        nanoseconds = np.round((start + 0.1 * np.arange(n)) * 1e9).astype(np.int64)
        stamps = nanoseconds // 10**9 + 1e-9 * (nanoseconds % 10**9)   # as a header's stamp
        sig = signals(y, np.zeros(n - 1))
        sig.t = stamps - start
        got.append(run_metrics(sig, None, 30.0, [0], 0.1))
    e2 = y[1:] ** 2
    assert got[0] == got[1]
    assert got[0]['cost_before'] == pytest.approx(e2[:300].mean())
    assert got[0]['cost_after'] == pytest.approx(e2[300:].mean())


def test_refusals_are_the_refused_model_events_by_cause():
    """Every refused event, two in one status too, each with its cause as its kind; the
    other outcomes are none (a version that would count a flown or queued model fails)."""
    sig = signals(np.zeros(8), np.zeros(7))
    sig.events = [(event('flew', 'unchecked'),), (event('refused', reason='check: a'),), (),
                  (event('queued', 'unchecked'), event('flew', 'check', 'check passed: x')),
                  (event('refused', 'weights', 'bad weights: nan'),
                   event('refused', reason='check: b')), (event('on_trial', 'unchecked'),),
                  (event('kept', reason='check passed: y'),)]
    assert refusals(sig) == [[1, 'check: a', 'check'], [4, 'bad weights: nan', 'weights'],
                             [4, 'check: b', 'check']]
    m = run_metrics(sig, None, None, [0], 0.1)
    assert m['refusals'] == [r[:2] for r in refusals(sig)]
    assert m['refusal_kinds'] == {'check': 2, 'weights': 1}


def test_a_revert_after_probation_is_counted_as_one_and_is_no_swap():
    """Model 2 flies at step 2 and is reverted to model 1 at step 5: one swap (2), one
    refusal of kind 'revert' with its whole status."""
    sig = signals(np.zeros(8), np.zeros(7), version=[1, 1, 2, 2, 2, 1, 1])
    sig.events = [()] * 7
    sig.events[2] = (event('flew', reason='check passed: better'),)
    sig.events[5] = (event('reverted', reason='check: worse'),)
    m = run_metrics(sig, None, None, [0], 0.1)
    assert m['swaps'] == [2] and m['adaptations'] == 1
    assert m['refusals'] == [[5, 'reverted: check: worse']]
    assert m['refusal_kinds'] == {'revert': 1}


def test_each_adapting_mode_is_paired_with_none_by_seed(tmp_path):
    """Two seeds: periodic costs 0.5x and 2x none's after the change (worse on 1 of 2, worst
    2, geometric mean 1); the refusals are counted by kind."""
    def seed(k, none, periodic, refused, kinds):
        return {'seed': k, 'theta': [0.0], 'runs': {
            'imaml/none': {'cost_after': none},
            'imaml/periodic': {'cost_after': periodic, 'refusals': refused,
                               'refusal_kinds': kinds}}}
    reports = [seed(0, 2.0, 1.0, [[40, 'check: x']], {'check': 1}),
               seed(1, 1.0, 2.0, [[40, 'check: y'], [90, 'bad weights: z']],
                    {'check': 1, 'weights': 1})]
    config = {'drift': {'modes': ['none', 'periodic'], 'methods': ['imaml'],
                        'constant_check': False}}
    report = drift_experiment_report(reports, str(tmp_path), config, 1.0)
    row = report['table']['imaml/periodic']
    assert row['vs_none']['values'] == [0.5, 2.0] and row['vs_none']['worse'] == 1
    assert row['vs_none']['worst'] == 2.0 and row['vs_none']['geomean'] == pytest.approx(1.0)
    assert row['refusals'] == [1, 2] and row['refusal_kinds'] == {'check': 2, 'weights': 1}
    assert report['table']['imaml/none']['vs_none'] is None
    md = (tmp_path / 'report.md').read_text()
    assert '| 1 of 2, 2, 1 |' in md and '3 (check 2, weights 1)' in md
