"""InnovationTest: the windowed chi-square test of normalised innovations (its false-alarm rate
against the chi-square tail, its delay on a step, what it leaves out)."""
import numpy as np
import pytest

from metampc_controller.innovation_test import InnovationTest


@pytest.mark.parametrize('window, alpha, n_y', [(10, 0.05, 2), (25, 0.01, 1)])
def test_false_alarms_on_standard_normal_innovations_come_at_the_rate_alpha(
        window, alpha, n_y):
    """nu ~ N(0, I): the window's sum is chi-square with W n_y degrees of freedom, so a full
    window rejects with probability alpha at any tick (Monte Carlo over 60000 ticks; the
    alarms of overlapping windows cluster, hence the loose bound). Fails on W degrees of
    freedom (10, 0.05, 2: 0.66) or on |nu| in place of |nu|^2."""
    test = InnovationTest(window, alpha, n_y)
    rng = np.random.default_rng(0)
    alarms = [test.update(nu) for nu in rng.standard_normal((60000, n_y))]
    rate = np.mean(alarms[window - 1:])
    assert alpha * 0.75 <= rate <= alpha * 1.25


def test_a_step_is_detected_after_the_analytic_number_of_ticks():
    """Zero innovations fill the window, then each output's jumps to 3: after j ticks the sum
    is 18 j; the chi-square 0.999 quantile of 40 degrees of freedom is 73.40 (tables), so the
    5th tick rejects (72 < 73.40 < 90). Fails on W degrees of freedom (quantile 45.3: the 3rd)
    or on |nu| in place of |nu|^2."""
    test = InnovationTest(20, 1e-3, 2)
    assert test.threshold == pytest.approx(73.402, abs=1e-3)
    assert not any(test.update(np.zeros(2)) for _ in range(40))
    ticks = [test.update(np.full(2, 3.0)) for _ in range(6)]
    assert ticks == [False] * 4 + [True, True]
    assert test.statistic == pytest.approx(18 * 6)


def test_nothing_is_tested_until_the_window_is_full_and_nan_ticks_do_not_count():
    test = InnovationTest(3, 1e-3, 1)
    big = np.array([100.0])
    assert not test.update(big) and not test.update(big)
    assert not test.update(np.array([np.nan]))       # not counted: the window holds 2
    assert test.update(big)                          # the third: full, 30000 > 16.3
    test.clear()
    assert test.statistic == 0.0 and not test.update(big)


def test_bad_settings_and_shapes_are_refused():
    for window, alpha, n_y in ((0, 0.1, 1), (5, 0.0, 1), (5, 1.0, 1), (5, 0.1, 0)):
        with pytest.raises(ValueError):
            InnovationTest(window, alpha, n_y)
    with pytest.raises(ValueError, match='2 outputs'):
        InnovationTest(5, 0.1, 2).update(np.zeros(3))
