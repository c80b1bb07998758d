"""The nonlinear MPC yardstick, checked where the answer is known independently."""
from dataclasses import dataclass, fields, replace
import math

import numpy as np
import pytest
import scipy.special
from scipy.linalg import expm
from scipy.optimize import lsq_linear

from metampc_controller.nmpc import Nmpc, NmpcConfig
from metampc_plant.integrate import rk4_sample
from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant, PlantConfig
from metampc_plant.steady_state import steady_output, steady_state

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


# --- the CasADi multiple-shooting solver (solver='ipopt') -------------------------------------

def test_linear_plant_equals_the_lq_tracking_answer():
    """theta = 0: van der Pol is a linear oscillator, and the NMPC's RK4 prediction a linear
    map x+ = A x + B u (read off the simulator's RK4 on unit vectors). Without bounds the
    problem is linear least squares over u_1..u_N (N = 15, tail 5, both outputs weighted),
    solved here by lstsq; the NMPC's plan equals it to 1e-6 (IPOPT's tolerance 1e-8). A wrong
    tail, Delta-u from the wrong u_0, outputs a sample off or weights swapped would not."""
    cfg = NmpcConfig(horizon=15, q=(1.0, 0.3), r=0.05, u_min=-np.inf, u_max=np.inf, tail=5)
    n, t = cfg.horizon, cfg.tail

    def step(x, u):
        return rk4_sample(VDP, np.atleast_2d(x), np.atleast_2d(u), np.zeros((1, 1)), cfg.dt,
                          cfg.substeps)[0]

    a = np.stack([step(e, [0.0]) for e in np.eye(2)], axis=1)
    b = step(np.zeros(2), [1.0])
    rng = np.random.default_rng(0)
    for _ in range(3):
        x0, u_prev = rng.uniform(-1.0, 1.0, 2), rng.uniform(-1.0, 1.0, 1)
        y_ref = rng.uniform(-1.0, 1.0, (n, 2))
        # Rows: sqrt(q) (y_k - r_k), k = 1..N+T (u_N held past N); sqrt(r) (u_k - u_{k-1}).
        sel = np.minimum(np.arange(n + t), n - 1)
        g, f, x = np.zeros((2 * (n + t), n)), np.zeros(2 * (n + t)), x0.copy()
        m = np.zeros((2, n))
        for k in range(n + t):
            x = a @ x
            m = a @ m
            m[:, sel[k]] += b
            g[2 * k:2 * k + 2], f[2 * k:2 * k + 2] = m, x
        sq = np.sqrt(np.tile(cfg.q, n + t))
        d = np.eye(n) - np.eye(n, k=-1)
        rows = np.vstack([sq[:, None] * g, np.sqrt(cfg.r) * d])
        rhs = np.r_[sq * (y_ref[sel].reshape(-1) - f),
                    np.sqrt(cfg.r) * np.r_[u_prev, np.zeros(n - 1)]]
        expected = np.linalg.lstsq(rows, rhs, rcond=None)[0]
        res = Nmpc(cfg, VDP, [0.0]).solve(x0, u_prev, y_ref)
        assert res.status == 'solved' and res.iterations >= 1 and res.residual < 1e-6
        np.testing.assert_allclose(res.u_plan[:, 0], expected, atol=1e-6)
        assert res.cost == pytest.approx(np.sum((rows @ expected - rhs) ** 2), rel=1e-9)


@pytest.mark.parametrize('name, theta, tail', [
    ('vanderpol', (1.8,), 0), ('vanderpol', (-0.8,), 0), ('pendulum', (1.2, 1.4, 0.1), 0),
    ('quadruple_tank', (0.45, 0.4), 10), ('quadruple_tank', (0.7, 0.6), 10)])
def test_ipopt_costs_no_more_than_lbfgsb(name, theta, tail):
    """On the same state, reference and bounds, the CasADi solution's cost is at most the
    L-BFGS-B yardstick's (its 50 iterations on forward differences), both from a cold start,
    over 20 samples (the tank: N = 10 and a tail of 10, L-BFGS-B's seconds kept short).
    Oscillators: random states of the initial-state box, set-points that are steady states
    at random inputs. The tank (with its tail; non-minimum-phase, g1 + g2 < 1, and not) as
    its experiment meets it: at the steady state of one row of its reference inputs, the
    set-point the steady output of another, u_t = 0 (the first tick) or random. (Both solve a
    non-convex problem: from a cold start far from the operating point, IPOPT may settle in a
    costlier local minimum, e.g. 3.53 against 3.39 from a random tank state; docs/mpc.md.)"""
    fam = get_family(name)
    rng = np.random.default_rng(1)
    lo, hi = np.asarray(fam.u_min), np.asarray(fam.u_max)
    if name == 'quadruple_tank':
        q, rows = (1.0, 1.0), [(3.0, 3.0), (2.6, 2.6), (3.4, 3.0), (2.8, 3.4)]
        cases = [(steady_state(fam, theta, rows[i]), steady_output(fam, theta, rows[j]), u)
                 for i, j, u in ((0, 1, np.zeros(2)), (1, 2, rng.uniform(lo, hi)),
                                 (2, 3, rng.uniform(lo, hi)))]
    else:
        q = (1.0, 0.0)
        cases = [(rng.uniform(fam.x0_low, fam.x0_high),
                  steady_output(fam, theta, rng.uniform(lo + 0.2 * (hi - lo),
                                                        hi - 0.4 * (hi - lo))),
                  rng.uniform(lo, hi)) for _ in range(3)]
    for x0, setpoint, u_prev in cases:
        y_ref = np.tile(setpoint, (20, 1))
        costs = {}
        for solver in ('ipopt', 'lbfgsb'):
            cfg = NmpcConfig(horizon=20 - tail, q=q, r=0.05, u_min=fam.u_min, u_max=fam.u_max,
                             dt=fam.dt, tail=tail, solver=solver)
            res = Nmpc(cfg, fam, theta).solve(x0, u_prev, y_ref[tail:])
            costs[solver] = res.cost, res.status
        assert costs['ipopt'][0] <= costs['lbfgsb'][0] * (1.0 + 1e-9), costs


def _vdp_after_one_solve(solver='ipopt'):
    cfg = NmpcConfig(horizon=10, r=0.05, solver=solver)
    ctrl = Nmpc(cfg, VDP, [1.0])
    ref = np.tile([0.8, 0.0], (cfg.horizon, 1))
    first = ctrl.solve(np.array([0.0, 0.0]), [0.0], ref)
    shifted = np.r_[first.u_plan[1:, 0], first.u_plan[-1, 0]]
    return ctrl, ref, shifted


def _break_ipopt(ctrl, outcome):
    """IPOPT's answer replaced: NaN (an evaluation gone wrong), or a finite plan that stopped
    unconverged at a cost above the shifted plan's (every input at its lower bound, from near
    rest towards 0.8)."""
    real = ctrl._shooting.solve

    def broken(*args, **kwargs):
        res = real(*args, **kwargs)
        u = np.full_like(res.u, np.nan if outcome == 'not finite' else -1.0)
        return replace(res, u=u, status='stopped: Maximum_Iterations_Exceeded', success=False)

    ctrl._shooting.solve = broken


@pytest.mark.parametrize('outcome', ['not finite', 'unconverged and worse'])
def test_an_unconverged_solve_flies_lbfgsb_from_the_same_start(outcome):
    """IPOPT fails (_break_ipopt): the plan is the one today's L-BFGS-B solver finds from the
    same shifted start (an NMPC of solver lbfgsb in the same state), the status says both."""
    ctrl, ref, shifted = _vdp_after_one_solve()
    old, _, _ = _vdp_after_one_solve('lbfgsb')
    old._plan = ctrl._plan
    _break_ipopt(ctrl, outcome)
    x1 = ctrl.rollout_state(np.zeros(2), [shifted[0]])
    res = ctrl.solve(x1, shifted[:1], ref)
    want = old.solve(x1, shifted[:1], ref)
    assert res.status == 'stopped: Maximum_Iterations_Exceeded (L-BFGS-B plan)'
    assert not res.fallback and res.cost == want.cost < np.inf
    np.testing.assert_array_equal(res.u_plan, want.u_plan)


def test_a_failed_solve_falls_back_to_the_shifted_plan():
    """IPOPT's plan and L-BFGS-B's both costlier than the shifted previous plan (every input
    at its lower bound): the shifted plan flies, fallback said, IPOPT's status reported."""
    ctrl, ref, shifted = _vdp_after_one_solve()
    _break_ipopt(ctrl, 'unconverged and worse')
    ctrl._solve_lbfgsb = lambda *args: (np.full_like(shifted, -1.0), 'solved', 1, math.nan)
    res = ctrl.solve(ctrl.rollout_state(np.zeros(2), [shifted[0]]), shifted[:1], ref)
    assert res.fallback and res.status == 'stopped: Maximum_Iterations_Exceeded'
    np.testing.assert_array_equal(res.u_plan[:, 0], shifted)
    assert np.isfinite(res.cost)


def test_a_measurement_that_is_not_finite_gives_a_finite_input_within_the_bounds():
    ctrl, ref, shifted = _vdp_after_one_solve()
    res = ctrl.solve(None, shifted[:1], ref, y=np.array([np.nan, 0.0]))
    assert res.fallback and res.status == 'stopped: invalid data'
    assert np.all(np.isfinite(res.u_plan)) and np.all(np.abs(res.u_plan) <= 1.0)
    np.testing.assert_array_equal(res.u_plan[:, 0], shifted)


@pytest.mark.parametrize('term, why', [
    (lambda v: scipy.special.expit(v), 'do not take CasADi symbols'),
    (np.vectorize(math.tanh), 'differ from the simulator')])
def test_a_family_without_a_symbolic_form_keeps_lbfgsb(term, why):
    """Equations through a function that takes arrays but no CasADi symbol: scipy's expit
    raises on one; np.vectorize(math.tanh) takes it silently and gives NaN, which the check
    against the simulator refuses. The NMPC says why and solves by L-BFGS-B, as before."""
    vdp = type(VDP)

    @dataclass(frozen=True)
    class Damped(vdp):
        def rhs(self, x, u, theta):
            return x[1], -x[0] - term(x[1]) + u[0]

    fam = Damped(**{f.name: getattr(VDP, f.name) for f in fields(VDP)})
    ctrl = Nmpc(NmpcConfig(horizon=5), fam, [0.0])
    assert ctrl.solver == 'lbfgsb' and why in ctrl.solver_note
    res = ctrl.solve(np.array([0.5, 0.0]), [0.0], np.zeros((5, 2)))
    assert res.status == 'solved' and np.isnan(res.residual)
