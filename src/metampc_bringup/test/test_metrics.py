"""Metric functions on plain arrays, against values worked out by hand."""
import math
from types import SimpleNamespace as Msg

from metampc_bringup.analysis.metrics import (bound_violations, compute_metrics, episodes,
                                              percentile_summary, reference_pairs, tick_accounting,
                                              tracking_metrics, version_segments)
from metampc_bringup.analysis.run_series import (CONTROL_INPUT, MPC_STATUS, PARAMETER_EVENT,
                                                 PLANT_OUTPUT, SeriesBuilder)
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


def _stamp(t):
    return Msg(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))


def _run(versions, events=()):
    """Outputs y_k = [k] (k = 0..len(versions)), statuses of steps 0..n-1 with reference 0 and
    the given config versions, and parameter events."""
    builder = SeriesBuilder()
    for k in range(len(versions) + 1):
        builder.add(PLANT_OUTPUT, Msg(step=k, header=Msg(stamp=_stamp(0.1 * k)), y=[float(k)],
                                      u_applied=[0.0], saturated=False, diverged=False))
    for k, version in enumerate(versions):
        builder.add(CONTROL_INPUT, Msg(step=k, header=Msg(stamp=_stamp(0.1 * k)), u=[0.0],
                                       model_version=1))
        builder.add(MPC_STATUS, Msg(
            step=k, header=Msg(stamp=_stamp(0.1 * k)), cost=0.0, solve_time=1e-4,
            tick_time=1e-3, iterations=5, fallback=False, terminal_fallback=False,
            model_version=1, solver_status='solved', planner='latent_mpc', y_ref=[0.0],
            q=[1.0], config_version=version))
    for event in events:
        builder.add(PARAMETER_EVENT, event)
    return builder.build()


def _event(t, node, changed=(), new=()):
    return Msg(stamp=_stamp(t), node=node, new_parameters=list(new), deleted_parameters=[],
               changed_parameters=list(changed))


def test_tracking_splits_at_each_config_version_and_only_when_it_changes():
    assert version_segments([0, 0, 1, 1, 1, 3]) == [(0, 2), (2, 5), (5, 6)]
    assert version_segments([]) == []
    plain = compute_metrics(_run([0] * 5))
    assert 'tracking_segments' not in plain and 'parameter_changes' not in plain
    r = Msg(name='r', value=Msg(type=8, double_array_value=[0.2]))
    declared = Msg(name='horizon', value=Msg(type=2, integer_value=20))
    m = compute_metrics(_run([0, 0, 1, 1, 1], events=[
        _event(0.0, '/controller', new=[declared]), _event(0.15, '/controller', changed=[r])]))
    # Status k pairs with output k + 1 = [k + 1] against the reference 0.
    assert [(s['config_version'], s['first_step'], s['last_step'], s['statuses'])
            for s in m['tracking_segments']] == [(0, 0, 1, 2), (1, 2, 4, 3)]
    assert [s['tracking']['cost'] for s in m['tracking_segments']] == [1 + 4, 9 + 16 + 25]
    assert m['tracking']['cost'] == 1 + 4 + 9 + 16 + 25
    assert m['parameter_changes'] == [{'stamp': pytest.approx(0.15), 'node': '/controller',
                                       'parameters': {'r': [0.2]}}]
