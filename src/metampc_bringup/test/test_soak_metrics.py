"""The soak's measures on timelines built by hand (times in ns at the observer)."""
import math

from metampc_common.node_main import EventCounts
from metampc_controller.controller_node import COUNTERS as CONTROLLER_COUNTERS
from metampc_plant.plant_node import COUNTERS as PLANT_COUNTERS
import pytest

from metampc_bringup.soak.soak_metrics import (deadlines, dropped, goals_met, observed_rate,
                                               process_usage, responses, stop_counts)

MIB = 2**20


def test_deadline_outcome_of_each_step():
    # y_k arrives at 1000 k; y_{k+1}.u_applied is the input the plant held over step k.
    applied = [0.0, 0.10, 0.11, 0.11, 0.12, 0.14, 0.14]
    ys = [(1000 * k, k, u) for k, u in enumerate(applied)]
    us = [(1000 * k + 500, k, u, 1) for k, u in
          [(0, 0.10), (1, 0.11), (2, 0.12), (4, 0.14), (5, 0.14), (6, 0.16)]]
    us.append((9000, 1, 0.99, 1))       # a second answer to step 1: the first one counts
    dl = deadlines(ys, us, start_ns=1000)
    # 0: before the start; 1: 0.11 applied, hit; 2: 0.12 answered, 0.11 still held, late;
    # 3: no answer; 4: hit; 5: the same input as step 4, undecidable; 6: no y_7 yet
    assert dl['outcome'] == {1: 'hit', 2: 'late', 3: 'unanswered', 4: 'hit', 5: 'ambiguous'}
    assert {k: dl[k] for k in ('steps', 'misses', 'late', 'unanswered', 'ambiguous')} == {
        'steps': 4, 'misses': 2, 'late': 1, 'unanswered': 1, 'ambiguous': 1}
    assert dl['miss_pct'] == 50.0
    assert dl['arrived'] == {k: 1000 * k for k in range(7)}


def test_no_decided_step_has_no_miss_percentage():
    assert math.isnan(deadlines([(0, 0, 0.0)], [], start_ns=0)['miss_pct'])
    assert deadlines([], [], start_ns=0)['steps'] == 0


def test_dropped_messages_by_hand():
    ys = [(t, step, 0.0) for t, step in [(0, 0), (1, 1), (2, 2), (4, 4), (5, 5), (7, 7)]]
    us = [(0, step, 0.0, 1) for step in (0, 1, 2, 5)]
    statuses = [(0, step, 1e-3, 1e-4, False) for step in (0, 1)]
    # measured from t = 1: steps 1, 2, 4, 5, 7 received (3 and 6 lost); 4 unanswered (7 is
    # the last: its answer may still be on its way); 2 and 5 answered without a status
    assert dropped(ys, us, statuses, start_ns=1) == {
        'y_missing': 2, 'u_missing': 1, 'status_missing': 2}
    assert dropped([], us, statuses, start_ns=0) == {
        'y_missing': 0, 'u_missing': 0, 'status_missing': 0}


def test_response_is_y_received_to_the_last_answer_received():
    ys = [(100, 1, 0.0), (200, 2, 0.0), (300, 3, 0.0)]
    us = [(150, 1, 0.0, 1), (260, 2, 0.0, 1), (270, 2, 0.0, 1)]
    assert responses(ys, us) == [(100, 50), (200, 70)]
    assert responses(ys, us, start_ns=150) == [(200, 70)]


def test_process_usage_over_the_measured_samples():
    samples = {'plant': [(0, 90 * MIB, 0.5), (1e9, 100 * MIB, 1.5), (3e9, 110 * MIB, 2.0),
                         (5e9, 105 * MIB, 3.0)],
               'controller': [(0, MIB, 0.0), (5e9, MIB, 1.0)]}    # one sample after start
    assert process_usage(samples, start_ns=1e9) == {'plant': {
        'rss_start_mb': 100.0, 'rss_end_mb': 105.0, 'rss_peak_mb': 110.0, 'growth_pct': 5.0,
        'cpu_pct': 37.5}}       # 1.5 CPU s over 4 s


def test_goals_are_inclusive_and_need_every_process():
    ok = {'plant': {'growth_pct': 5.0}, 'controller': {'growth_pct': -1.0}}
    assert goals_met({'miss_pct': 0.1}, ok)
    assert not goals_met({'miss_pct': 0.1001}, ok)
    assert not goals_met({'miss_pct': math.nan}, ok)
    assert not goals_met({'miss_pct': 0.0}, {**ok, 'controller': {'growth_pct': 5.01}})


def test_observed_rate():
    assert observed_rate([(k * 10_000_000, k, 0.0) for k in range(101)]) == pytest.approx(100.0)
    assert math.isnan(observed_rate([(0, 0, 0.0)]))


def _summary(names, values):
    events = EventCounts(None, names)       # the nodes' own counters and their stop-line text
    events.counts.update(zip(names, values))
    return events.summary()


def test_stop_counts_of_the_nodes_stop_lines():
    values = tuple(3 + 2 * i for i in range(len(PLANT_COUNTERS)))     # distinct
    plant = ('[INFO] [1717171717.123456789] [plant]: stopped at step 6003 after 2 reset(s): '
             + _summary(PLANT_COUNTERS, values))
    assert stop_counts('[INFO] [plant]: started\n' + plant + '\n') == dict(
        zip(PLANT_COUNTERS, values))
    values = tuple(118 - 7 * i for i in range(len(CONTROLLER_COUNTERS)))     # distinct
    controller = '[INFO] [1.5] [controller]: stopped at step 120: ' + _summary(
        CONTROLLER_COUNTERS, values)
    earlier = '[INFO] [1.0] [controller]: stopped at step 3: ' + _summary(
        CONTROLLER_COUNTERS, (1,) * len(CONTROLLER_COUNTERS))
    assert stop_counts(earlier + '\n' + controller) == dict(zip(CONTROLLER_COUNTERS, values))


def test_no_stop_line_no_counts():
    assert stop_counts('') == {}
    assert stop_counts('[INFO] [controller]: stopped before any sample: 0 answered') == {}
