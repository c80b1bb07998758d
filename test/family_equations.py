"""The shipped plant families' equations written out again from docs/families.md (not imported
from the families), and their integration by scipy: the independent reference of the family
tests (core and node)."""
import math

import numpy as np
from scipy.integrate import solve_ivp


def vanderpol(x, u, th):
    return [x[1], th[0] * x[1] * (1 - x[0] ** 2) - x[0] + u[0]]


def duffing(x, u, th):
    delta, alpha, beta = th
    return [x[1], -delta * x[1] - alpha * x[0] - beta * x[0] ** 3 + u[0]]


def pendulum(x, u, th):
    m, length, b = th
    return [x[1], -(9.81 / length) * math.sin(x[0]) - b / (m * length ** 2) * x[1]
            + u[0] / (m * length ** 2)]


def quadruple_tank(x, u, th):
    big_a = [28.0, 32.0, 28.0, 32.0]
    a = [0.071, 0.057, 0.071, 0.057]
    k1, k2 = 3.33, 3.35
    g1, g2 = th
    s = [math.sqrt(2 * 981 * max(h, 0.0)) for h in x]
    return [-a[0] / big_a[0] * s[0] + a[2] / big_a[0] * s[2] + g1 * k1 / big_a[0] * u[0],
            -a[1] / big_a[1] * s[1] + a[3] / big_a[1] * s[3] + g2 * k2 / big_a[1] * u[1],
            -a[2] / big_a[2] * s[2] + (1 - g2) * k2 / big_a[2] * u[1],
            -a[3] / big_a[3] * s[3] + (1 - g1) * k1 / big_a[3] * u[0]]


def cascaded_tanks(x, u, th):
    """Each tank gains its net inflow; at its rim (9.9 V) it starts to spill, linearly more up
    to all of the excess at 10 V; the upper tank's spill sends k5 u into the lower one."""
    k1, k2, k3, k4, k5 = th

    def spill_share(level):
        if level <= 9.9:
            return 0.0
        return 1.0 if level >= 10.0 else (level - 9.9) / 0.1

    def gain(net, level):
        return net - spill_share(level) * net if net > 0 else net

    upper = math.sqrt(max(x[0], 0.0))
    lower = math.sqrt(max(x[1], 0.0))
    return [gain(k4 * u[0] - k1 * upper, x[0]),
            gain(k2 * upper - k3 * lower + k5 * u[0] * spill_share(x[0]), x[1])]


EQUATIONS = {'vanderpol': vanderpol, 'duffing': duffing, 'pendulum': pendulum,
             'quadruple_tank': quadruple_tank, 'cascaded_tanks': cascaded_tanks}
OUTPUT_GAIN = {'quadruple_tank': np.array([[0.5, 0, 0, 0], [0, 0.5, 0, 0]]),
               'cascaded_tanks': np.array([[0.0, 1.0]])}


def one_step(name, x, u, theta, dt):
    """The state after dt from x with u held, by DOP853 at tight tolerances."""
    sol = solve_ivp(lambda _t, z: EQUATIONS[name](z, u, theta), (0.0, dt), x,
                    method='DOP853', rtol=1e-12, atol=1e-12)
    return sol.y[:, -1]
