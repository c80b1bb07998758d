"""The planner contract's shared settings: declared once, checked alike for both planners, and
still the controller's node parameters of the same names."""
import dataclasses

import pytest

from metampc_controller.controller_params import MPC
from metampc_controller.mpc import MpcConfig
from metampc_controller.nmpc import NmpcConfig
from metampc_controller.planner import PlannerConfig
from metampc_common.params import table

SHARED = ('horizon', 'q', 'r', 'u_min', 'u_max')


def test_the_shared_fields_are_declared_once():
    """Both configs take the very field declarations of PlannerConfig (default, range,
    description), and the node's MPC parameters keep their names and order."""
    base = dataclasses.fields(PlannerConfig)
    assert tuple(f.name for f in base) == SHARED
    for cls in (MpcConfig, NmpcConfig):
        assert all(a is b for a, b in zip(dataclasses.fields(cls)[:len(base)], base)), cls
    assert list(table([MPC])) == [*SHARED, 'offset_free', 'disturbance_gain', 'y_min', 'y_max',
                                  'soft_penalty', 'max_iter', 'time_limit', 'eps_abs',
                                  'eps_rel']


@pytest.mark.parametrize('cls', [MpcConfig, NmpcConfig])
@pytest.mark.parametrize('bad, message', [
    ({'horizon': 0}, 'horizon must be >= 1'),
    ({'q': (-1.0, 0.0)}, 'q must be a vector of finite weights >= 0'),
    ({'r': 0.0}, r'r must be finite and > 0'),
    ({'u_min': 0.5, 'u_max': 0.2}, r'need u_min <= u_max'),
    ({'u_min': float('nan')}, r'need u_min <= u_max'),
    ({'r': (0.1, 0.1), 'u_min': (-1.0, -1.0, -1.0)}, 'one value per input'),
])
def test_both_planners_refuse_the_same_bad_settings(cls, bad, message):
    """Before, NmpcConfig took any value and the NMPC checked only some (a negative output
    weight or a NaN bound was planned with)."""
    with pytest.raises(ValueError, match=message):
        cls(**bad)


def test_another_planner_takes_the_shared_values():
    mpc = MpcConfig(horizon=7, q=(1.0, 0.5), r=(0.3,), u_min=(-0.4,), u_max=(0.6,))
    nmpc = NmpcConfig(**mpc.shared(), dt=0.05)
    assert [getattr(nmpc, name) for name in SHARED] == [getattr(mpc, name) for name in SHARED]
    assert nmpc.dt == 0.05 and nmpc.bounds(2)[1].tolist() == [0.6, 0.6]
