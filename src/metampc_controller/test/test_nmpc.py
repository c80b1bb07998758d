"""The nonlinear MPC yardstick, checked where the answer is known independently."""
from dataclasses import replace

import numpy as np
from scipy.linalg import expm
from scipy.optimize import lsq_linear

from metampc_controller.nmpc import Nmpc, NmpcConfig
from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant, PlantConfig

VDP = get_family('vanderpol')


def _lsq_plan(cfg: NmpcConfig, x0, u_prev, y_ref):
    """theta = 0 makes the plant a linear oscillator: the problem is bounded least squares."""
    a_c = np.array([[0.0, 1.0], [-1.0, 0.0]])
    b_c = np.array([0.0, 1.0])
    # Exact zero-order-hold discretisation through the augmented matrix exponential.
    m = expm(np.block([[a_c, b_c[:, None]], [np.zeros((1, 3))]]) * cfg.dt)
    a_d, b_d = m[:2, :2], m[:2, 2]
    n = cfg.horizon
    g = np.zeros((2 * n, n))
    f = np.zeros(2 * n)
    x = np.asarray(x0, float)
    for k in range(n):
        x = a_d @ x
        f[2 * k:2 * k + 2] = x
        for j in range(k + 1):
            g[2 * k:2 * k + 2, j] = np.linalg.matrix_power(a_d, k - j) @ b_d
    sq = np.sqrt(np.tile(np.asarray(cfg.q, float), n))
    d = np.eye(n) - np.eye(n, k=-1)
    d0 = np.zeros(n)
    d0[0] = u_prev
    a_ls = np.vstack([sq[:, None] * g, np.sqrt(cfg.r) * d])
    b_ls = np.concatenate([sq * (y_ref.reshape(-1) - f), np.sqrt(cfg.r) * d0])
    return lsq_linear(a_ls, b_ls, bounds=(cfg.u_min, cfg.u_max), tol=1e-12).x


def test_linear_case_matches_bounded_least_squares():
    cfg = NmpcConfig(horizon=15, q=(1.0, 0.1), r=0.05, u_min=-1.0, u_max=1.0, max_iter=200)
    y_ref = np.tile([0.8, 0.0], (cfg.horizon, 1))
    for x0, u_prev in (([0.0, 0.0], 0.0), ([-1.0, 0.5], 0.3), ([2.0, -1.0], -1.0)):
        plan = Nmpc(cfg, VDP, [0.0]).solve(np.array(x0), [u_prev], y_ref).u_plan[:, 0]
        expected = _lsq_plan(cfg, x0, u_prev, y_ref)
        assert np.max(np.abs(plan - expected)) < 2e-3, (x0, plan, expected)
    # The third case saturates: the bounds are active and respected.
    assert np.isclose(np.abs(expected).max(), 1.0)


def test_closed_loop_tracks_a_setpoint_on_an_unstable_plant():
    theta = -0.5  # unstable origin, as for half of N(0, 1)
    cfg = NmpcConfig(horizon=20, r=0.05)
    plant = Plant(PlantConfig(theta=(theta,), dt=cfg.dt, substeps=10))
    ctrl = Nmpc(cfg, VDP, [theta])
    y, u_prev = plant.reset(), 0.0
    ref = np.tile([0.5, 0.0], (cfg.horizon, 1))
    us = []
    for _ in range(50):
        res = ctrl.solve(plant.x, [u_prev], ref)
        assert ctrl.u_min[0] <= res.u[0] <= ctrl.u_max[0]
        u_prev = float(res.u[0])
        us.append(u_prev)
        y = plant.step([u_prev])
    assert not plant.diverged
    assert abs(y[0] - 0.5) < 0.02


def test_two_inputs_and_unmeasured_states_on_the_quadruple_tank():
    """The 4-state, 2-input family: the NMPC sees only 0.5 (h1, h2) and fills in h3, h4 from its
    model; it brings both measured levels to set-points off the operating point (reachable:
    the steady state of v = (4, 3.5) V for this theta, computed below by the simulator)."""
    tank = get_family('quadruple_tank')
    theta = (0.7, 0.6)                       # minimum phase (g1 + g2 > 1)
    steady = Plant(PlantConfig(family='quadruple_tank', theta=theta))
    for _ in range(400):                     # 2000 s at v = (4, 3.5) V: settled
        target = steady.step([4.0, 3.5])
    cfg = NmpcConfig(horizon=10, q=(1.0, 1.0), r=0.01, u_min=0.0, u_max=10.0, dt=tank.dt)
    ctrl = Nmpc(cfg, tank, theta)
    plant = Plant(PlantConfig(family='quadruple_tank', theta=theta))
    y, u = plant.output(), np.array([3.0, 3.0])
    ref = np.tile(target, (cfg.horizon, 1))
    for _ in range(80):                      # 400 s
        res = ctrl.solve(None, u, ref, y)     # the state estimated from y
        assert res.u.shape == (2,) and np.all((0.0 <= res.u) & (res.u <= 10.0))
        u = res.u
        y = plant.step(u)
    assert np.abs(y - target).max() < 0.02, (y, target)
    # The estimate of the unmeasured levels converged to the plant's.
    assert np.abs(ctrl._x - plant.x).max() < 1e-3


def test_the_tail_costs_the_plan_held_past_the_horizon():
    """tail T: J of a plan equals, with the tail off, J over N + T of the plan with its last
    input held T more samples against the reference with its last row kept (the same costs
    without the tail's own code), on the tank's two inputs and outputs."""
    tank = get_family('quadruple_tank')
    theta = (0.7, 0.6)
    short = NmpcConfig(horizon=6, q=(1.0, 0.5), r=(0.01, 0.02), u_min=0.0, u_max=10.0,
                       dt=tank.dt, tail=4)
    long_ = NmpcConfig(horizon=10, q=(1.0, 0.5), r=(0.01, 0.02), u_min=0.0, u_max=10.0,
                       dt=tank.dt)
    rng = np.random.default_rng(3)
    plans = rng.uniform(1.0, 6.0, (5, 6, 2))
    y_ref = rng.uniform(2.0, 8.0, (6, 2))
    x0, u_prev = np.array([6.0, 5.0, 2.0, 1.5]), np.array([3.0, 3.0])
    got = Nmpc(short, tank, theta).costs(x0, u_prev, y_ref, plans.reshape(5, -1))
    held = np.concatenate([plans, np.repeat(plans[:, -1:], 4, axis=1)], axis=1)
    ref = np.concatenate([y_ref, np.repeat(y_ref[-1:], 4, axis=0)])
    want = Nmpc(long_, tank, theta).costs(x0, u_prev, ref, held.reshape(5, -1))
    np.testing.assert_allclose(got, want, rtol=1e-12)
    untailed = Nmpc(replace(short, tail=0), tank, theta).costs(
        x0, u_prev, y_ref, plans.reshape(5, -1))
    assert np.all(got > untailed)
