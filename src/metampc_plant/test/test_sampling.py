"""The bridge's sampling rule against answers worked out by hand, and the live stream against
the whole-grid function on the same samples."""
import math

from metampc_plant.sampling import grid_step, hold, SampleStream
import numpy as np

# Samples at irregular stamps (s), each value naming its sample; the grid every 0.1 s.
STAMPS = [0.0, 0.03, 0.07, 0.125, 0.25, 0.25]
VALUES = [[1.0], [2.0], [3.0], [4.0], [5.0], [6.0]]
GRID = [-0.1, 0.0, 0.1, 0.2, 0.25, 0.3, 0.4, 0.5]
# By hand, stale after 0.2 s: t=-0.1 none; 0.0 -> sample 1 (age 0); 0.1 -> 3 (0.07); 0.2 -> 4
# (0.125); 0.25 -> 6 (the later of two at 0.25, age 0: a stamp equal to t_k counts); 0.3 -> 6;
# 0.4 -> 6 (age 0.15); 0.5 -> age 0.25 > 0.2: stale.
HELD = [math.nan, 1.0, 3.0, 4.0, 6.0, 6.0, 6.0, math.nan]


def test_hold_takes_the_newest_sample_at_or_before_each_tick_and_marks_stale_ones():
    values, fresh = hold(STAMPS, VALUES, GRID, stale_timeout=0.2)
    np.testing.assert_array_equal(values[:, 0], HELD)
    assert fresh.tolist() == [not math.isnan(v) for v in HELD]
    values, fresh = hold([], np.zeros((0, 2)), GRID, 0.2)
    assert values.shape == (len(GRID), 2) and not fresh.any() and np.isnan(values).all()


def test_the_live_stream_holds_as_the_grid_function_whatever_the_arrival_order():
    rng = np.random.default_rng(3)
    stamps = np.sort(rng.uniform(0.0, 5.0, 200))
    values = rng.normal(size=(200, 2))
    grid = np.arange(0.0, 5.5, 0.1)
    want, fresh = hold(stamps, values, grid, stale_timeout=0.08)
    stream = SampleStream()
    order = rng.permutation(200)
    for t, expected, ok in zip(grid, want, fresh):
        # Whatever arrived by now (a sample may come late, out of order), all up to t.
        for i in [i for i in order if stamps[i] <= t]:
            stream.add(stamps[i], values[i])
        order = [i for i in order if stamps[i] > t]
        got, age = stream.at(t)
        assert (got is not None and age <= 0.08) == ok
        if ok:
            np.testing.assert_array_equal(got, expected)
    assert len(stream._stamps) == 1     # only the sample held at the last tick is kept


def test_grid_step_counts_whole_periods_and_never_repeats_a_step():
    assert grid_step(None, 0.0, 0.1) == 0
    assert grid_step(2, 0.3, 0.1) == 3           # 0.3 / 0.1 = 2.9999999999999996
    assert grid_step(3, 0.3995, 0.1) == 4        # fired a little early
    assert grid_step(4, 0.73, 0.1) == 7          # missed two periods: steps 5 and 6 skipped
