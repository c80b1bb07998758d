"""Parameters of the controller node -> ControllerConfig, and every range check, in-process."""
import math
import re

import pytest

from metampc_common import renames
from metampc_common.params import ParameterError
from metampc_controller.controller_params import parse_params, PARAMETERS


def values(**changes):
    """Parameter values as ROS hands them over: the defaults with some changed."""
    out = {name: spec.default for name, spec in PARAMETERS.items()}
    out.update(changes)
    return out


def test_defaults_are_the_paper_task_at_10_hz():
    cfg = parse_params(values())
    mpc = cfg.mpc
    assert (cfg.rate_hz, cfg.planner, cfg.n_y, cfg.n_u, cfg.active, cfg.history) == (
        10.0, 'latent_mpc', 2, 1, True, 0)
    assert (mpc.horizon, tuple(mpc.q), mpc.r, mpc.u_min, mpc.u_max) == (
        20, (1.0, 0.0), (0.05,), (-1.0,), (1.0,))
    assert cfg.reference_kind == 'setpoint_sequence'
    assert cfg.reference_params == {'n_y': 2, 'outputs': (0,), 'setpoints': (0.8, -0.5, 0.3, -0.8),
                                    'segment': 7.5, 'start': 0.0}
    assert (cfg.pre_model_input, cfg.excitation.kind) == ('zero', 'random_hold')


def test_values_are_converted_and_combined():
    cfg = parse_params(values(rate_hz=50, horizon=10, q=[2, 0.5], u_min=-0.5,
                              excitation_amplitude=0.8, pre_model_input='excitation',
                              reference='steps', reference_times=[1, 2.5],
                              reference_values=[0.5, -0.5], reference_initial=0.1,
                              reference_outputs=[0, 1], active=False))
    assert isinstance(cfg.rate_hz, float) and cfg.rate_hz == 50.0   # an integer for a double
    assert cfg.mpc.horizon == 10 and tuple(cfg.mpc.q) == (2.0, 0.5)
    # The excitation: the middle 0.8 of the input range [-0.5, 1].
    lo, hi = cfg.excitation.band()
    assert lo == pytest.approx([-0.35]) and hi == pytest.approx([0.85]) and cfg.n_u == 1
    assert (cfg.excitation.u_min, cfg.excitation.u_max) == ((-0.5,), (1.0,))
    tank = parse_params(values(u_min=[0, 0], u_max=[10, 10], r=[0.1, 0.2], q=[1, 1]))
    assert (tank.n_u, tank.n_y, tank.mpc.r) == (2, 2, (0.1, 0.2))
    assert [list(b) for b in tank.excitation.band()] == [[0.0, 0.0], [10.0, 10.0]]
    # An operating region inside wide bounds: 3 V +- 0.4 x 5 V on both pumps.
    region = parse_params(values(u_min=[0, 0], u_max=[10, 10], r=[0.1, 0.2], q=[1, 1],
                                 excitation_center=[3.0, 3.0], excitation_amplitude=0.4))
    assert [list(b) for b in region.excitation.band()] == [[1.0, 1.0], [5.0, 5.0]]
    assert cfg.reference_params == {'n_y': 2, 'outputs': (0, 1), 'initial': 0.1,
                                    'steps': ((1.0, 0.5), (2.5, -0.5))}
    assert not cfg.active and cfg.pre_model_input == 'excitation'
    sine = parse_params(values(reference='sine', reference_period=4.0, reference_amplitude=0.2))
    assert sine.reference_params['period'] == 4.0 and sine.reference_params['amplitude'] == 0.2
    setpoint = parse_params(values(reference='setpoint', reference_values=[-0.3]))
    assert setpoint.reference_params['value'] == -0.3
    assert parse_params(values(reference='setpoint')).reference_params['value'] == 0.0
    rows = parse_params(values(reference_per_output=True, reference_outputs=[1, 0],
                               reference_values=[6.0, 6.5, 5.0, 7.25]))
    assert rows.reference_params['setpoints'] == [(6.0, 6.5), (5.0, 7.25)]


@pytest.mark.parametrize('center, amplitude, error', [
    ([3.0, 3.0], 0.8, 'excitation_center [3.0, 3.0] +- excitation_amplitude x half the range '
                      '[4.0, 4.0], leaves the input bounds'),      # 3 - 4 < 0
    ([3.0], 0.2, 'excitation_center needs one value per input (2)'),
])
def test_an_excitation_band_outside_the_bounds_is_refused(center, amplitude, error):
    with pytest.raises(ParameterError, match=re.escape(error)):
        parse_params(values(u_min=[0, 0], u_max=[10, 10], r=[0.1, 0.2], q=[1, 1],
                            excitation_center=center, excitation_amplitude=amplitude))


BAD = {
    'rate_hz 0': ({'rate_hz': 0.0}, 'rate_hz must be > 0'),
    'rate_hz inf': ({'rate_hz': math.inf}, 'rate_hz must be finite'),
    'rate_hz text': ({'rate_hz': 'fast'}, 'rate_hz must be a number'),
    'horizon 0': ({'horizon': 0}, 'horizon must be >= 1'),
    'horizon float': ({'horizon': 2.5}, 'horizon must be an integer'),
    'q negative': ({'q': [1.0, -1.0]}, 'q must be >= 0'),
    'q empty': ({'q': []}, 'q needs one weight per plant output'),
    'q text': ({'q': 'one'}, 'q must be a list of numbers'),
    'r 0': ({'r': 0.0}, 'r must be > 0'),
    'bounds': ({'u_min': 1.0, 'u_max': 0.0}, 'need u_min <= u_max'),
    'planner': ({'planner': 'pid'}, 'planner must be one of latent_mpc, nmpc'),
    'bounds length': ({'u_min': [0.0, 0.0], 'u_max': [1.0, 1.0, 1.0]},
                      'need one value per input'),
    'reference': ({'reference': 'ramp'}, 'reference must be one of'),
    'outputs': ({'reference_outputs': [2]}, 'outputs must be indices in [0, 2)'),
    'setpoint values': ({'reference': 'setpoint', 'reference_values': [1.0, 2.0]},
                        'reference setpoint takes one value'),
    'steps': ({'reference': 'steps', 'reference_values': [1.0]}, 'reference steps needs'),
    'steps order': ({'reference': 'steps', 'reference_times': [2.0, 1.0],
                     'reference_values': [1.0, 2.0]}, 'increasing times'),
    'sine period': ({'reference': 'sine', 'reference_period': 0.0}, 'period must be > 0'),
    'rows width': ({'reference_per_output': True, 'reference_outputs': [0, 1],
                    'reference_values': [1.0, 2.0, 3.0]},
                   'reference_values must hold 2 values (one per reference output) per'),
    'rows kind': ({'reference_per_output': True, 'reference': 'sine'},
                  'reference_per_output applies to setpoint_sequence, not sine'),
    'sequence segment': ({'reference_segment': -1.0}, 'reference_segment must be > 0'),
    'pre-model': ({'pre_model_input': 'noise'}, 'pre_model_input must be one of'),
    'excitation kind': ({'excitation_kind': 'multisine'}, 'excitation_kind must be one of'),
    'amplitude': ({'excitation_amplitude': 0.0}, 'excitation_amplitude must be in (0, 1]'),
    'amplitude above 1': ({'excitation_amplitude': 1.5},
                          'excitation_amplitude must be in (0, 1]'),
    'hold': ({'excitation_hold_s': 0.0}, 'hold_s'),
    'seed': ({'excitation_seed': -1}, 'excitation_seed must be >= 0'),
    'max_iter': ({'max_iter': 0}, 'max_iter must be >= 1'),
    'time_limit': ({'time_limit': 0.0}, 'time_limit must be > 0'),
    'eps_abs': ({'eps_abs': 0.0}, 'eps_abs must be > 0'),
    'eps_rel': ({'eps_rel': -1e-3}, 'eps_rel must be >= 0'),
    'history': ({'history': -3}, 'history must be in [0, 1000]'),
    'active': ({'active': 'yes'}, 'active must be true or false'),
}


@pytest.mark.parametrize('case', sorted(BAD))
def test_bad_values_name_the_parameter(case):
    changes, message = BAD[case]
    with pytest.raises(ParameterError, match=re.escape(message)):
        parse_params(values(**changes))


def test_reference_paper_is_the_setpoint_sequence_with_one_warning(monkeypatch, capsys):
    monkeypatch.setattr(renames, '_written', set())     # not yet written in this process
    old = [parse_params(values(reference='paper')) for _ in range(2)]
    assert old[0] == old[1] == parse_params(values(reference='setpoint_sequence'))
    assert capsys.readouterr().err == ("warning: reference: 'paper' is renamed "
                                       "'setpoint_sequence'; the old value will be removed in "
                                       'the next release\n')


def test_a_trial_shorter_than_the_horizon_is_refused():
    """model_check_trial: 0 (no trial) or at least N samples, else its check scores nothing."""
    with pytest.raises(ParameterError, match='model_check_trial must be 0 or at least horizon'):
        parse_params(values(model_check_trial=10, horizon=20))
    assert parse_params(values(model_check_trial=20, horizon=20)).gate.model_check_trial \
        == 20
    assert parse_params(values(model_check_trial=0, horizon=20)).gate.model_check_trial \
        == 0
