"""The families' equations on CasADi symbols (nmpc_shooting.symbolic_sample) against the
simulator's numpy RK4. The solver built on them: test_nmpc.py."""
import numpy as np
import pytest

from metampc_controller.nmpc_shooting import symbolic_sample
from metampc_plant.integrate import rk4_sample
from metampc_plant.registry import get_family

FAMILIES = ('vanderpol', 'duffing', 'pendulum', 'quadruple_tank', 'cascaded_tanks')


@pytest.mark.parametrize('name', FAMILIES)
def test_symbolic_sample_equals_the_simulators(name):
    """The families' equations on CasADi symbols (one RK4 sample and the output) against the
    numpy RK4 the simulator runs, on random states around the initial-state box (beyond it
    too: the tanks' max(h, 0) and the overflow's clip on both sides), inputs and thetas: to
    1e-12. A symbolic twin with a sign, a constant or the output's timing wrong would fail."""
    fam = get_family(name)
    rng = np.random.default_rng(7)
    n = 200
    lo, hi = np.asarray(fam.x0_low) - 1.0, np.asarray(fam.x0_high) + 2.0
    x = rng.uniform(lo, hi, (n, fam.n_x))
    u = rng.uniform(fam.u_min, fam.u_max, (n, fam.n_u))
    theta = fam.sample_theta(rng, n)
    sample = symbolic_sample(fam, 0.3 * fam.dt, 2)
    x_sym, y_sym = sample.map(n)(x.T, u.T, theta.T)
    x_num = rk4_sample(fam, x, u, theta, 0.3 * fam.dt, 2)
    y_num = np.stack(fam.output(x_num.T, u.T, theta.T), axis=1)
    np.testing.assert_allclose(np.asarray(x_sym).T, x_num, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(y_sym).T, y_num, rtol=1e-12, atol=1e-12)
