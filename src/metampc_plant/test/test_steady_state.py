"""Steady states against the quadruple tank's closed form (Johansson 2000): at constant pump
voltages each tank's outflow a_i sqrt(2 g h_i) equals its inflow."""
import numpy as np
import pytest

from metampc_plant.families.quadruple_tank import GRAVITY, OUTLET, PUMP, SENSOR
from metampc_plant.registry import get_family
from metampc_plant.steady_state import steady_output, steady_state

TANK = get_family('quadruple_tank')


def closed_form(theta, u):
    """Levels h1..h4 (cm) from the inflows: h = (q / a)^2 / (2 g)."""
    (g1, g2), (v1, v2), (k1, k2) = theta, u, PUMP
    inflow = np.array([g1 * k1 * v1 + (1 - g2) * k2 * v2, g2 * k2 * v2 + (1 - g1) * k1 * v1,
                       (1 - g2) * k2 * v2, (1 - g1) * k1 * v1])
    return (inflow / np.asarray(OUTLET)) ** 2 / (2 * GRAVITY)


@pytest.mark.parametrize('theta, u', [((0.553, 0.485), (3.0, 3.2)), ((0.384, 0.715), (2.0, 4.5)),
                                      ((0.8, 0.3), (9.5, 0.5))])
def test_tank_steady_state_is_the_closed_form(theta, u):
    h = closed_form(theta, u)
    np.testing.assert_allclose(steady_state(TANK, theta, u), h, rtol=1e-8)
    np.testing.assert_allclose(steady_output(TANK, theta, u), SENSOR * h[:2], rtol=1e-8)


def test_inputs_outside_the_bounds_or_no_steady_state_are_refused():
    with pytest.raises(ValueError, match=r'input \[11.0, 3.0\] is not 2 values inside'):
        steady_state(TANK, (0.5, 0.5), (11.0, 3.0))
    # Full pumps fill tank 1 to 112.8 cm at the steady state: beyond the 100-cm state box.
    assert closed_form((0.5, 0.5), (10.0, 10.0))[0] == pytest.approx(112.8, abs=0.1)
    with pytest.raises(ValueError, match='no steady state inside the state box'):
        steady_state(TANK, (0.5, 0.5), (10.0, 10.0))
