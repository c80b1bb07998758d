"""Reference signals: values at the horizon's sample times, checked against hand-written ones."""
import numpy as np
import pytest

from metampc_controller.references import (
    make_reference, Setpoint, SetpointSequence, SetpointSequenceConfig, Sine, Steps)


def test_setpoint_fills_the_tracked_output_only():
    ref = make_reference('setpoint', value=0.7)
    assert isinstance(ref, Setpoint)
    out = ref.evaluate(3.0, 0.1, 4)
    np.testing.assert_array_equal(out, [[0.7, 0.0]] * 4)


def test_steps_switch_at_their_times_despite_rounding():
    ref = make_reference('steps', steps=[(0.5, 1.0), (1.0, -2.0)], initial=0.25)
    assert isinstance(ref, Steps)
    out = ref.evaluate(0.0, 0.1, 12)[:, 0]                  # samples 0.1, 0.2, ..., 1.2
    np.testing.assert_array_equal(out, [0.25] * 4 + [1.0] * 5 + [-2.0] * 3)
    # 7.3 + 0.1 computes to 7.3999999999999995: still the sample of the step at 7.4.
    ref = make_reference('steps', steps=[(7.4, 1.0)])
    assert 7.3 + 0.1 < 7.4
    np.testing.assert_array_equal(ref.evaluate(7.3, 0.1, 2)[:, 0], [1.0, 1.0])


def test_sine_at_the_sample_times():
    ref = make_reference('sine', amplitude=2.0, period=4.0, offset=0.5, phase=0.3)
    assert isinstance(ref, Sine)
    times = [1.25, 1.5, 1.75]
    expected = [0.5 + 2.0 * np.sin(2.0 * np.pi * t / 4.0 + 0.3) for t in times]
    np.testing.assert_allclose(ref.evaluate(1.0, 0.25, 3)[:, 0], expected, rtol=1e-12)


def test_setpoint_sequence_is_the_paper_task_by_default():
    ref = make_reference('setpoint_sequence')
    assert isinstance(ref, SetpointSequence)
    assert SetpointSequenceConfig().duration == 30.0
    out = ref.evaluate(0.0, 0.1, 320)
    # Sample k (t = k / 10, k = 1..320) lies in segment k // 75 (7.5 s = 75 samples).
    levels = [0.8, -0.5, 0.3, -0.8]
    expected = [levels[min(k // 75, 3)] for k in range(1, 321)]
    np.testing.assert_array_equal(out[:, 0], expected)
    assert np.all(out[:, 1] == 0.0)
    assert ref.evaluate(-5.0, 0.1, 3)[0, 0] == 0.8          # before the start: the first one


def test_chosen_outputs_and_sizes():
    out = make_reference('setpoint', value=1.5, n_y=3, outputs=(0, 2)).evaluate(0.0, 0.1, 2)
    np.testing.assert_array_equal(out, [[1.5, 0.0, 1.5]] * 2)


@pytest.mark.parametrize('kind,params', [
    ('ramp', {}), ('setpoint', {'amplitude': 1.0}), ('steps', {'steps': [(1.0, 0.0), (0.5, 1.0)]}),
    ('sine', {'period': 0.0}), ('setpoint', {'outputs': (2,)}),
    ('setpoint_sequence', {'setpoints': ()})])
def test_invalid_references_are_rejected(kind, params):
    with pytest.raises(ValueError):
        make_reference(kind, **params)


@pytest.mark.parametrize('kind,params', [
    ('setpoint_sequence', {}),
    ('setpoint_sequence', dict(start=1.05, segment=2.5, outputs=(0, 1))),
    ('steps', dict(steps=[(0.0, 0.5), (7.4, -0.5), (7.5, 0.1), (12.0, 0.2)], initial=-0.3)),
    ('setpoint', dict(value=0.3, n_y=3, outputs=(2,))),
    ('sine', dict(amplitude=0.4, period=3.3, outputs=(0, 1)))])
def test_references_equal_the_signal_at_the_sample_times(kind, params):
    ref = make_reference(kind, **params)
    outputs = list(ref.config.outputs)
    for dt in (0.1, 0.05, 0.01, 0.3):
        for n in (1, 20, 7, 20, 50):
            for k in range(0, 1200, 3):
                t0 = k * dt
                expected = np.zeros((n, ref.config.n_y))
                expected[:, outputs] = ref.signal(t0 + dt * np.arange(1, n + 1))[:, None]
                got = ref.evaluate(t0, dt, n)
                assert got.dtype == np.float64
                np.testing.assert_array_equal(got, expected)


def test_setpoint_rows_give_each_output_its_own_value_on_both_paths():
    """Rows (y2, y1) on outputs (1, 0) of three outputs: written by hand for a horizon inside
    one segment (the constant path) and for one across the switch at 2 s (the signal path)."""
    ref = make_reference('setpoint_sequence', n_y=3, outputs=(1, 0),
                         setpoints=[(6.0, 6.5), (5.0, 7.25)], segment=2.0)
    np.testing.assert_array_equal(ref.evaluate(0.0, 0.5, 2), [[6.5, 6.0, 0.0]] * 2)
    np.testing.assert_array_equal(ref.evaluate(1.0, 0.5, 3),     # 1.5 s; 2 s and 2.5 s
                                  [[6.5, 6.0, 0.0], [7.25, 5.0, 0.0], [7.25, 5.0, 0.0]])
    np.testing.assert_array_equal(ref.evaluate(9.0, 0.5, 1), [[7.25, 5.0, 0.0]])
    single = make_reference('setpoint_sequence', setpoints=[(0.3,), (-0.2,)], segment=1.0)
    np.testing.assert_array_equal(single.evaluate(0.0, 0.5, 2)[:, 0], [0.3, -0.2])  # 0.5, 1 s


@pytest.mark.parametrize('setpoints', [[(1.0, 2.0), 3.0], [(1.0, 2.0, 3.0)], [(1.0,)]])
def test_setpoint_rows_must_be_all_rows_of_one_value_per_output(setpoints):
    with pytest.raises(ValueError, match='all numbers or all rows of 2 values'):
        SetpointSequenceConfig(outputs=(0, 1), setpoints=setpoints)
