"""The median pruner's rule, decided on the worker (pruning.py).

Independent answers: block means and medians computed by hand with numpy, and Optuna's own
MedianPruner on the same trials (test_search runs the rule through a whole search).
"""
import math

import numpy as np
import optuna
from optuna.distributions import FloatDistribution
from optuna.trial import create_trial, TrialState

from metampc_bringup.studies.pruning import (MedianRule, NO_MEDIAN, pruned_at, REPORT_EVERY,
                                             reports)


def test_reports_are_the_means_of_each_full_block_of_losses():
    losses = [float(k) for k in range(35)]          # the last 5 make no report yet
    assert reports(losses) == [4.5, 14.5, 24.5]
    losses[10:20] = [math.nan] * 10                 # a block without a finite loss
    losses[20] = math.inf                           # non-finite losses are left out
    got = reports(losses)
    assert got[0] == 4.5 and math.isnan(got[1]) and got[2] == np.mean(range(21, 30))


def _study(rule: MedianRule, completed):
    """An in-memory study with the rule's pruner and COMPLETE trials of the given reports."""
    study = optuna.create_study(pruner=rule.pruner())
    for values in completed:
        study.add_trial(create_trial(
            state=TrialState.COMPLETE, value=0.0, params={'x': 0.5},
            distributions={'x': FloatDistribution(0.0, 1.0)},
            intermediate_values={(i + 1) * REPORT_EVERY: v for i, v in enumerate(values)}))
    return study


def test_thresholds_are_the_median_of_the_complete_trials_after_start_up_and_warm_up():
    rule = MedianRule(iterations=5 * REPORT_EVERY, startup_trials=3,
                      warmup_steps=2 * REPORT_EVERY)
    assert rule.steps == (10, 20, 30, 40, 50)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    assert rule.thresholds(_study(rule, [[1, 2, 3, 4, 5]] * 2)) is None   # start-up: 2 < 3
    done = [[5, 4, 3, 2, 1], [9, 8, 7, 6], [1, 1, 1, 1, 1], [2, 2, 2]]
    got = rule.thresholds(_study(rule, done))
    assert math.isnan(got[0])                       # step 10 < warm-up 20
    for i, step in enumerate(rule.steps[1:], start=1):
        at = [d[i] for d in done if len(d) > i]
        assert got[i] == float(np.median(at)), step   # by hand: 3.0, 2.5, 2, 1
    assert got[1:] == (3.0, 2.5, 2.0, 1.0)
    one = MedianRule(60, startup_trials=1)          # nobody reported past step 10
    assert one.thresholds(_study(one, [[1.0]])) == (1.0,) + (NO_MEDIAN,) * 5


def test_pruned_at_is_the_first_report_whose_best_so_far_is_above_its_threshold():
    off = math.nan
    thresholds = (off, 3.0, 2.5, 2.0, 1.0)
    assert pruned_at([9, 2.9, 2.4, 1.9, 1.5], thresholds) == 50    # 1.5 > 1.0 at step 50
    assert pruned_at([9, 4.0], thresholds) == 20
    assert pruned_at([9, 2.0, 9, 9, 9], thresholds) == 50          # best so far: 2.0
    assert pruned_at([9, 2.0, 9], thresholds) is None              # nor at 30: runs on
    assert pruned_at([math.nan, math.nan], (1.0, 1.0)) == 10       # nothing finite: pruned
    assert pruned_at([5.0], (NO_MEDIAN,)) is None                  # no median there: only NaN


def test_the_rule_agrees_with_optunas_median_pruner():
    """For a running trial with the same reports, pruned_at on the thresholds stops at the
    step where MedianPruner.prune first says so."""
    rule = MedianRule(iterations=6 * REPORT_EVERY, startup_trials=2,
                      warmup_steps=REPORT_EVERY)
    rng = np.random.default_rng(4)
    done = [list(rng.uniform(0, 2, 6)) for _ in range(5)]
    study = _study(rule, done)
    thresholds = rule.thresholds(study)
    for _ in range(30):
        given = list(rng.uniform(0, 2, 6))
        optunas = None
        for i in range(6):
            trial = create_trial(state=TrialState.RUNNING, params={'x': 0.5},
                                 distributions={'x': FloatDistribution(0.0, 1.0)},
                                 intermediate_values={(j + 1) * REPORT_EVERY: given[j]
                                                      for j in range(i + 1)})
            if rule.pruner().prune(study, trial):
                optunas = (i + 1) * REPORT_EVERY
                break
        assert pruned_at(given, thresholds) == optunas, given


def test_a_nan_report_of_a_complete_trial_is_left_out_of_the_median_as_optuna_does():
    """Complete trials reporting 1, NaN and 3 at a step: the threshold is 2 (the median of
    1 and 3), and a running trial reporting 2.5 there is pruned, by the rule and by Optuna's
    MedianPruner alike; with NaN counted, the median would be NaN and nothing pruned."""
    rule = MedianRule(iterations=REPORT_EVERY, startup_trials=1)
    study = _study(rule, [[1.0], [math.nan], [3.0]])
    assert rule.thresholds(study) == (2.0,)
    for report, pruned in ((2.5, True), (1.5, False)):
        trial = create_trial(state=TrialState.RUNNING, params={'x': 0.5},
                             distributions={'x': FloatDistribution(0.0, 1.0)},
                             intermediate_values={REPORT_EVERY: report})
        assert rule.pruner().prune(study, trial) == pruned
        assert pruned_at([report], rule.thresholds(study)) == (REPORT_EVERY if pruned else None)
