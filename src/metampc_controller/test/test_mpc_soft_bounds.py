"""Soft output bounds of the latent MPC (MpcConfig.y_min / y_max / soft_penalty).

The independent answer: the same problem written out by simulating the model input by input
(not from mpc.py's condensed matrices), with explicit slack variables, solved by scipy's
trust-constr (an interior-point method: nothing shared with OSQP's ADMM).
"""
import numpy as np
import pytest
from scipy.linalg import expm
from scipy.optimize import Bounds, LinearConstraint, minimize

from metampc_model.latent_model import LatentModel
from metampc_controller.mpc import LatentMpc, MpcConfig

TIGHT = dict(eps_abs=1e-9, eps_rel=1e-9, max_iter=200000, time_limit=30.0, polish=True,
             offset_free='none')
N = 10


def oscillator(dt: float = 0.2) -> LatentModel:
    """A lightly damped oscillator (it overshoots a step): y = x, u = x1 at rest."""
    a_c = np.array([[0.0, 1.0], [-1.0, -0.3]])
    b_c = np.array([[0.0], [1.0]])
    m = expm(np.block([[a_c, b_c], [np.zeros((1, 3))]]) * dt)
    return LatentModel(A=m[:2, :2], B=m[:2, 2:], C=np.eye(2), e=np.zeros(2), d=np.zeros(2))


def reference_plan(mpc: LatentMpc, model: LatentModel, z0, u_prev, y_ref, y_max, rho):
    """min J(U) + rho sum(s) s.t. y_{1..N,0} <= y_max + s, s >= 0, |u| <= 1 (trust-constr)."""
    term = mpc.terminal
    q, r = np.asarray(mpc.config.q), float(mpc.config.r)

    def outputs(plan):
        z, ys = np.array(z0, dtype=float), []
        for u in plan:
            z = model.step(z, np.array([u]))
            ys.append(model.output(z))
        return np.array(ys), z

    def steady(r1):
        mat = np.block([[model.A - np.eye(2), model.B], [model.C[:1], np.zeros((1, 1))]])
        return np.linalg.solve(mat, np.concatenate([-model.e, [r1 - model.d[0]]]))

    t_fac = np.linalg.cholesky(term.P).T

    def residual(plan):
        ys, z_n = outputs(plan)
        return np.concatenate([(np.sqrt(q) * (ys[:-1] - y_ref[:-1])).ravel(),
                               t_fac @ (np.r_[z_n, plan[-1]] - steady(y_ref[-1, 0])),
                               np.sqrt(r) * np.diff(np.r_[u_prev, plan])]), ys[:, 0]

    # Residual and y1 are affine in the plan: their columns are the responses to unit inputs.
    base, y_base = residual(np.zeros(N))
    cols = [residual(np.eye(N)[j]) for j in range(N)]
    mat = np.column_stack([c[0] - base for c in cols])
    y_mat = np.column_stack([c[1] - y_base for c in cols])

    def cost(x):
        res = mat @ x[:N] + base
        return float(res @ res) + rho * float(np.sum(x[N:]))

    hess = np.zeros((2 * N, 2 * N))
    hess[:N, :N] = 2.0 * mat.T @ mat

    def grad(x):
        return np.r_[2.0 * mat.T @ (mat @ x[:N] + base), np.full(N, rho)]

    # y1 - s <= y_max and |u| <= 1, s >= 0, as scipy's LinearConstraint and Bounds.
    cons = LinearConstraint(np.hstack([y_mat, -np.eye(N)]), -np.inf, y_max - y_base)
    bounds = Bounds(np.r_[np.full(N, -1.0), np.zeros(N)], np.r_[np.ones(N), np.full(N, np.inf)])
    res = minimize(cost, np.zeros(2 * N), jac=grad, hess=lambda x: hess, method='trust-constr',
                   bounds=bounds, constraints=[cons], options=dict(gtol=1e-11, xtol=1e-13,
                                                                   maxiter=20000))
    assert res.status in (1, 2), res.message
    return res.x[:N], res.x[N:]


def solve(y_max, rho=1e3, z0=(0.0, 0.0), u_prev=(0.0,), setpoint=0.8):
    model = oscillator()
    mpc = LatentMpc(MpcConfig(horizon=N, q=(1.0, 0.0), r=0.05, y_max=y_max, soft_penalty=rho,
                              **TIGHT))
    mpc.set_model(model)
    y_ref = np.zeros((N, 2))
    y_ref[:, 0] = setpoint
    res = mpc.solve(np.asarray(z0, dtype=float), np.asarray(u_prev, dtype=float), y_ref)
    return mpc, model, y_ref, res


def test_loose_bounds_change_nothing():
    free = solve(())[3]
    loose = solve((5.0, np.inf))[3]
    np.testing.assert_allclose(loose.u_plan, free.u_plan, atol=1e-7)
    assert loose.slack < 1e-9 and not loose.fallback


def test_active_bound_is_met_and_matches_an_independent_solver():
    """The unbounded plan overshoots 0.8 (oscillator): with y1 <= 0.82 it must not, and the
    plan is the exact-penalty problem's optimum (SLSQP on the simulated model)."""
    free = solve(())[3]
    assert free.y_pred[:, 0].max() > 0.83
    mpc, model, y_ref, res = solve((0.82, np.inf))
    assert res.y_pred[:, 0].max() <= 0.82 + 1e-6 and res.slack < 1e-6
    plan, slack = reference_plan(mpc, model, np.zeros(2), np.zeros(1), y_ref, 0.82, 1e3)
    np.testing.assert_allclose(res.u_plan[:, 0], plan, atol=1e-4)


def test_an_impossible_bound_gives_a_plan_and_reports_its_violation():
    """From x1 = 1 moving up at 1/s, y1 <= 0.5 cannot hold at the next samples: the plan
    exists (no fallback), violates as little as the penalty makes worth it, and says so."""
    mpc, model, y_ref, res = solve((0.5, np.inf), z0=(1.0, 1.0), u_prev=(1.0,), setpoint=0.5)
    assert not res.fallback and res.status == 'solved'
    violation = res.y_pred[:, 0].max() - 0.5
    assert violation > 0.1
    assert res.slack == pytest.approx(violation, abs=1e-5)
    plan, slack = reference_plan(mpc, model, np.array([1.0, 1.0]), np.array([1.0]), y_ref, 0.5,
                                 1e3)
    np.testing.assert_allclose(res.u_plan[:, 0], plan, atol=1e-4)
    assert res.slack == pytest.approx(slack.max(), abs=1e-4)


def test_bad_bounds_are_one_clear_error():
    with pytest.raises(ValueError, match=r'soft output bounds need y_min <= y_max'):
        MpcConfig(y_min=(1.0, 0.0), y_max=(0.0, 1.0))
    with pytest.raises(ValueError, match=r'y_max needs one value per output \(2\)'):
        MpcConfig(y_max=(1.0,))
