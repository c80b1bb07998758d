"""The cascaded_tanks family against its equations written out again (test/family_equations.py,
integrated by scipy's DOP853): one-step errors below 1e-6 away from the rims and small across
them, steady states in closed form with and without overflow, and its prior around the fit."""
from family_equations import one_step
import numpy as np
import pytest

from metampc_plant.cascaded_tanks_data import load_cascaded_tanks
from metampc_plant.families.cascaded_tanks import FIT_THETA, FIT_X0, SPREAD
from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant, PlantConfig
from metampc_plant.steady_state import steady_state

FAMILY = get_family('cascaded_tanks')


def test_one_step_error_against_scipy_below_and_across_the_rims():
    """Along the estimation record's first 300 inputs (the upper tank overflows near sample
    150), from the fitted start: RK4 at the default 10 substeps against DOP853, one sample at
    a time. Away from the rims (9.9..10 V) the RK4 error, O(h^5), stays below 1e-6; a sample
    that enters the rim band integrates the kink of the spill and errs more (measured 1.8e-4 V;
    bound 1e-3 V), still far below the sensor noise (SNR 40 dB: ~0.05 V)."""
    u = load_cascaded_tanks().u_est[:300]
    plant = Plant(PlantConfig(family='cascaded_tanks', x0=FIT_X0))
    away, across = 0.0, 0.0
    for v in u:
        start = plant.x
        reference = one_step('cascaded_tanks', start, [v], FIT_THETA, FAMILY.dt)
        y = plant.step([v])
        error = max(np.abs(plant.x - reference).max(), abs(y[0] - reference[1]))
        if max(start.max(), reference.max()) < 9.85:
            away = max(away, error)
        else:
            across = max(across, error)
    assert across > 0.0, 'the record should reach the rim'
    assert away < 1e-6 and across < 1e-3, (away, across)


@pytest.mark.parametrize('v', [1.0, 2.5])
def test_steady_state_without_overflow_is_the_closed_form(v):
    # inflow = outflow in each tank: k4 v = k1 sqrt(x1), k2 sqrt(x1) = k3 sqrt(x2)
    k1, k2, k3, k4, _ = FIT_THETA
    x1 = (k4 * v / k1) ** 2
    x2 = (k2 / k3) ** 2 * x1
    assert x2 < x1 < 9.9
    assert np.allclose(FAMILY.rhs([x1, x2], [v], FIT_THETA), 0.0, atol=1e-15)
    assert np.allclose(steady_state(FAMILY, FIT_THETA, [v]), [x1, x2], rtol=1e-9)


def test_a_full_upper_tank_stays_at_10_V_and_feeds_the_lower_one():
    """k4 v / k1 > sqrt(10): the upper tank fills to its 10 V rim and stays there, the lower
    one settles where k2 sqrt(10) + k5 v = k3 sqrt(x2) (overflow share included); with a
    larger share the lower tank fills to its rim too."""
    v = 5.0
    theta = (0.055, 0.02, 0.04, 0.05, 0.01)
    plant = Plant(PlantConfig(family='cascaded_tanks', theta=theta, x0=(5.0, 3.0)))
    for _ in range(1500):
        y = plant.step([v])
    k1, k2, k3, k4, k5 = theta
    assert (k4 * v / k1) ** 2 > 10.0
    expected = ((k2 * np.sqrt(10.0) + k5 * v) / k3) ** 2          # 8.02 V (2.5 without k5)
    assert plant.x[0] == pytest.approx(10.0, abs=1e-6)
    assert y[0] == pytest.approx(expected, abs=1e-6) and expected < 9.9
    plant.reset(theta=(0.055, 0.02, 0.04, 0.05, 0.03), x0=(5.0, 3.0))
    for _ in range(1500):
        y = plant.step([v])
    assert plant.x[0] == pytest.approx(10.0, abs=1e-6) and y[0] == pytest.approx(10.0, abs=1e-6)


def test_prior_is_within_the_spread_of_the_fit_and_x2_is_measured():
    for component, fitted in zip(FAMILY.theta, FIT_THETA):
        assert component.distribution == 'uniform'
        assert component.a == pytest.approx((1 - SPREAD) * fitted, abs=1e-6)
        assert component.b == pytest.approx((1 + SPREAD) * fitted, abs=1e-6)
    assert FAMILY.x0 == FIT_X0 and FAMILY.dt == 4.0
    assert FAMILY.output([7.0, 4.2], [1.0], FIT_THETA) == (4.2,)
    assert list(FAMILY.state_from_output(np.array([4.2]), np.array([7.0, 3.0]))) == [7.0, 4.2]
