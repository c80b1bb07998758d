"""Offset-free tracking (offset_free.py and its use in mpc.py), against independent answers.

The plant is a linear oscillator simulated exactly (zero-order hold); the MPC's model is the
same oscillator with a constant input disturbance the model does not know, or with its input
gain 20 % off. The encoder is the identity (z_t = x_t), as for a measured state. The exact
answer at a set-point is zero steady offset; the paper's eq. (mpc) ('none') keeps one.

Tolerance of the offset: 1e-6. OSQP runs at 1e-9 here, so the plan meets the QP's optimum to
~1e-9; at the closed-loop steady state the estimate is the exact model mismatch (no filter lag
left after 400 steps of a loop whose slowest pole is ~0.95: 0.95^400 ~ 1e-9), so what is left
is solver tolerance times the loop's gain, far below 1e-6, while 'none' leaves offsets of
1e-2..1e-1 in the same runs.
"""
import warnings

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.optimize import lsq_linear

from metampc_model.latent_model import LatentModel
from metampc_controller.mpc import LatentMpc, MpcConfig
from metampc_controller.offset_free import (detectability_rank, DisturbanceEstimator,
                                            disturbance_model, SteadyStateTarget)
from metampc_controller.terminal_cost import terminal_cost

TIGHT = dict(eps_abs=1e-9, eps_rel=1e-9, max_iter=100000, time_limit=10.0)


def oscillator(gain: float = 1.0, dt: float = 0.1) -> LatentModel:
    """x1'' + x1' + x1 = gain * u at zero-order hold; y = x (so x1 = v needs u = v / gain)."""
    a_c = np.array([[0.0, 1.0], [-1.0, -1.0]])
    b_c = np.array([[0.0], [1.0]])
    m = expm(np.block([[a_c, b_c], [np.zeros((1, 3))]]) * dt)
    return LatentModel(A=m[:2, :2], B=gain * m[:2, 2:], C=np.eye(2), e=np.zeros(2),
                       d=np.zeros(2))


def closed_loop(form: str, plant: LatentModel, model: LatentModel, setpoints,
                u_dist: float = 0.0, steps: int = 400, **cfg) -> tuple:
    """(y_1 - r per step (steps,), the last PlanResult) of the MPC on `model` driving `plant`
    from rest, the plant's input being u + u_dist; setpoints: one value, or one per step."""
    mpc = LatentMpc(MpcConfig(horizon=20, q=(1.0, 0.0), r=0.05, offset_free=form, **TIGHT,
                              **cfg))
    mpc.set_model(model)
    x, u = np.zeros(2), np.zeros(1)
    ref = np.zeros((20, 2))
    r1 = np.broadcast_to(np.asarray(setpoints, dtype=float), (steps,))
    errors = np.empty(steps)
    for t in range(steps):
        ref[:, 0] = r1[t]
        res = mpc.solve(x, u, ref, plant.output(x), t)
        u = res.u.copy()
        x = plant.step(x, u + u_dist)
        errors[t] = plant.output(x)[0] - r1[t]
    return errors, res


def settling(errors: np.ndarray, tol: float = 5e-3) -> int:
    """First step from which |error| stays below tol."""
    outside = np.nonzero(np.abs(errors) >= tol)[0]
    return 0 if outside.size == 0 else int(outside[-1]) + 1


@pytest.mark.parametrize('form', ['state', 'input'])
@pytest.mark.parametrize('case', ['input disturbance', 'gain 20 % off'])
def test_zero_steady_offset(form, case):
    kwargs = dict(u_dist=0.2) if case == 'input disturbance' else {}
    model = oscillator(1.2 if case == 'gain 20 % off' else 1.0)
    errors, res = closed_loop(form, oscillator(), model, 0.5, **kwargs)
    assert abs(errors[-1]) < 1e-6
    off, _ = closed_loop('none', oscillator(), model, 0.5, **kwargs)
    assert abs(off[-1]) > 1e-2          # what the paper's eq. (mpc) leaves: the test can fail
    if form == 'input' and case == 'input disturbance':
        # The input form's estimate is the disturbance itself (same model otherwise).
        assert res.disturbance == pytest.approx([0.2], abs=1e-6)


def test_unreachable_setpoint_holds_the_bound_without_windup():
    """x1 = 3 needs u = 2.9 > u_max = 1: the input sits at the bound, x1 at 1.1. When the
    set-point comes back to 0.5 the loop settles as fast as a loop that had asked for the
    reachable 1.1 all along (an integrator of the tracking error would still be unwinding),
    with zero offset."""
    plant, model = oscillator(), oscillator(1.2)
    errors, res = closed_loop('state', plant, model, np.r_[np.full(300, 3.0), np.full(300, 0.5)],
                              u_dist=0.1, steps=600)
    assert errors[299] == pytest.approx(1.1 - 3.0, abs=1e-3)    # u + u_dist = 1.1 held
    reachable, _ = closed_loop('state', plant, model,
                               np.r_[np.full(300, 1.1), np.full(300, 0.5)], u_dist=0.1,
                               steps=600)
    assert abs(reachable[299]) < 1e-3
    assert settling(errors[300:]) <= settling(reachable[300:]) + 2
    assert abs(errors[-1]) < 1e-6


def test_output_form_refuses_an_integrating_mode():
    """An output disturbance and a mode at eigenvalue 1 look alike from y (Pannocchia &
    Rawlings 2003): the rank test refuses the model; 'state' accepts it."""
    model = LatentModel(A=np.diag([1.0, 0.5]), B=np.array([[0.1], [1.0]]), C=np.eye(2),
                        e=np.zeros(2), d=np.zeros(2))
    with pytest.raises(ValueError, match=r'not detectable, rank .* = 3 < n_z \+ n_d = 4 '
                                         r'\(A has an eigenvalue at 1'):
        disturbance_model(model, 'output')
    with pytest.raises(ValueError, match='not detectable'):
        LatentMpc(MpcConfig(offset_free='output')).set_model(model)
    assert disturbance_model(model, 'state').rank == 2 + 4
    # The same A without the integrator passes the output form.
    stable = LatentModel(A=np.diag([0.9, 0.5]), B=model.B, C=model.C, e=model.e, d=model.d)
    assert disturbance_model(stable, 'output').rank == 4


def test_rank_matches_pbh_at_one():
    """rank [[A - I, B_d], [C, C_d]] for the input form = n_z + n_u exactly when the plant has
    no transmission zero at 1 (det of the square system matrix at z = 1 non-zero)."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b, c = rng.normal(size=(3, 3)), rng.normal(size=(3, 1)), rng.normal(size=(1, 3))
        square = np.block([[a - np.eye(3), b], [c, np.zeros((1, 1))]])
        full = abs(np.linalg.det(square)) > 1e-9
        assert (detectability_rank(a, c, b, np.zeros((1, 1))) == 4) == full


def test_estimator_skips_a_gap_and_resets():
    model = oscillator()
    est = DisturbanceEstimator(model, disturbance_model(model, 'input'), gain=1.0)
    x, u = np.zeros(2), np.array([0.3])
    est.update(x, u, model.output(x), step=0)
    x1 = model.step(x, u + 0.5)                       # disturbance 0.5 over step 1
    assert est.update(x1, u, model.output(x1), step=1) == pytest.approx([0.5])
    x2 = model.step(model.step(x1, u), u)             # two undisturbed steps: a gap
    assert est.update(x2, u, model.output(x2), step=3) == pytest.approx([0.5])
    est.reset()
    assert est.p == pytest.approx([0.0])


def test_bounded_target_against_brute_force():
    """The bounded steady state minimises the tracked output error over the input box (grid
    search over u); within the bounds it is the unconstrained KKT solution."""
    model = oscillator(0.8)
    mpc = LatentMpc(MpcConfig(q=(1.0, 0.0), u_min=-1.0, u_max=1.0))
    mpc.set_model(model)
    term = mpc.terminal
    target = SteadyStateTarget(model, np.array([1.0, 0.0]), term.ss_r, term.ss_e,
                               np.array([-1.0]), np.array([1.0]), bounded=True)
    for r1 in (0.4, 2.0, -3.0):
        s = target(np.r_[r1, 0.0, model.e, model.d], np.empty(3))
        grid = np.linspace(-1.0, 1.0, 20001)
        best = grid[np.argmin(np.abs(0.8 * grid - r1))]
        assert s[2] == pytest.approx(best, abs=1e-4)
        z = np.linalg.solve(np.eye(2) - model.A, model.B[:, 0] * s[2])
        assert s[:2] == pytest.approx(z, abs=1e-9)


@pytest.mark.parametrize('n_u', [1, 2])
def test_bounded_target_equals_box_least_squares(n_u):
    """On random models, weights, bounds and references (n_u = 1, 2: every family's), the
    active-set target equals the box least squares of scipy's BVLS (an exact active-set
    solver: the independent answer) to 1e-9, u_s and z_s, wherever the unconstrained u_s
    leaves the box (some inputs bounded on one side only); a target that ignored a bound,
    picked a non-optimal active set or clipped the unconstrained u_s (not optimal with two
    coupled inputs) would fail."""
    rng = np.random.default_rng(n_u)
    checked = 0
    for _ in range(200):
        n_z, n_y = int(rng.integers(2, 6)), int(rng.integers(n_u, 4))
        a = rng.normal(size=(n_z, n_z))
        a *= rng.uniform(0.3, 0.95) / max(abs(np.linalg.eigvals(a)))
        model = LatentModel(A=a, B=rng.normal(size=(n_z, n_u)), C=rng.normal(size=(n_y, n_z)),
                            e=rng.normal(size=n_z), d=rng.normal(size=n_y))
        q = rng.uniform(0.5, 2.0, n_y)
        q[rng.integers(n_y)] *= rng.integers(0, 2)       # sometimes an output not tracked
        if np.count_nonzero(q) < n_u:
            continue
        u_min = -rng.uniform(0.1, 2.0, n_u)
        u_max = rng.uniform(0.1, 2.0, n_u)
        if rng.random() < 0.2:
            u_min[rng.integers(n_u)] = -np.inf        # an input bounded on one side only
        term = terminal_cost(model, q, np.full(n_u, 0.1), 1e-8)
        target = SteadyStateTarget(model, q, term.ss_r, term.ss_e, u_min, u_max, bounded=True)
        const = np.r_[model.e, model.d] + rng.normal(size=n_z + n_y)     # e', d'
        r_n = 5.0 * rng.normal(size=n_y)
        s = target(np.r_[r_n, const], np.empty(n_z + n_u))
        free = np.linalg.solve(np.eye(n_z) - a, np.c_[model.B, const[:n_z]])
        t = q > 0
        w = np.sqrt(q[t])[:, None]
        gain = model.C[t] @ free[:, :n_u]
        rhs = r_n[t] - const[n_z:][t] - model.C[t] @ free[:, n_u]
        u_star = lsq_linear(w * gain, w[:, 0] * rhs, bounds=(u_min, u_max), method='bvls',
                            tol=1e-14).x
        unconstrained = term.ss_r @ r_n + np.hstack([term.ss_e, -term.ss_r]) @ const
        if np.all((unconstrained[n_z:] >= u_min) & (unconstrained[n_z:] <= u_max)):
            continue
        checked += 1
        assert s[n_z:] == pytest.approx(u_star, abs=1e-9)
        assert s[:n_z] == pytest.approx(free @ np.r_[u_star, 1.0], abs=1e-9)
    assert checked > 100


def test_bounded_target_with_an_output_disturbance_against_brute_force():
    """With d' = d + p != 0 the target must meet r - d' (the plant's output is the model's
    plus d'): y1 at steady state is 0.8 u + d'_1 (the oscillator's gain, by hand), u_s the
    grid point closest to it in the box. At r = 0 with d'_1 = 1.5 the bound is -1 (a target
    that added d' would pick +1); at r = 1.7, u_s = 0.25 inside the box."""
    model = oscillator(0.8)
    mpc = LatentMpc(MpcConfig(q=(1.0, 0.0), u_min=-1.0, u_max=1.0))
    mpc.set_model(model)
    term = mpc.terminal
    target = SteadyStateTarget(model, np.array([1.0, 0.0]), term.ss_r, term.ss_e,
                               np.array([-1.0]), np.array([1.0]), bounded=True)
    d_out = np.array([1.5, -0.4])
    grid = np.linspace(-1.0, 1.0, 20001)
    for r1, want in ((0.0, -1.0), (1.7, 0.25), (3.0, 1.0), (-2.0, -1.0)):
        s = target(np.r_[r1, 0.0, model.e, d_out], np.empty(3))
        best = grid[np.argmin(np.abs(0.8 * grid + d_out[0] - r1))]
        assert best == pytest.approx(want, abs=1e-12)
        assert s[2] == pytest.approx(best, abs=1e-4)
        z = np.linalg.solve(np.eye(2) - model.A, model.B[:, 0] * s[2])
        assert s[:2] == pytest.approx(z, abs=1e-9)


def biased_oscillator() -> LatentModel:
    """The oscillator with its own constants e, d != 0."""
    plain = oscillator()
    return LatentModel(A=plain.A, B=plain.B, C=plain.C, e=np.array([0.05, -0.02]),
                       d=np.array([0.3, -0.2]))


@pytest.mark.parametrize('form', ['state', 'input', 'output'])
def test_a_model_fed_its_own_outputs_estimates_no_disturbance(form):
    """The residual's constant holds the model's own e and d: on the model's exact outputs
    (e, d != 0) every form estimates p = 0; one that left out e or d would estimate them."""
    model = biased_oscillator()
    est = DisturbanceEstimator(model, disturbance_model(model, form), gain=0.5)
    x = np.array([0.2, -0.1])
    rng = np.random.default_rng(5)
    for t in range(20):
        u = rng.uniform(-1.0, 1.0, 1)
        x = model.step(x, u)
        p = est.update(x, u, model.output(x), step=t)
    assert p == pytest.approx(np.zeros_like(p), abs=1e-12)


def test_the_estimate_moves_by_g_of_the_residual_per_step():
    """A constant latent disturbance w on the model's own data ('state' form: p = [w; v],
    the one-step residual gives [w; 0]): after n updates p = (1 - (1 - g)^n) [w; 0], at
    g = 0.3 (where g and 1 - g differ)."""
    model = biased_oscillator()
    est = DisturbanceEstimator(model, disturbance_model(model, 'state'), gain=0.3)
    w = np.array([0.1, -0.05])
    x, u = np.array([0.2, -0.1]), np.array([0.4])
    est.update(x, u, model.output(x), step=0)
    for n in range(1, 4):
        x = model.step(x, u) + w
        p = est.update(x, u, model.output(x), step=n)
        assert p == pytest.approx(np.r_[(1 - 0.7 ** n) * w, 0.0, 0.0], abs=1e-12)


def test_a_non_finite_sample_is_refused_counted_and_leaves_no_trace():
    """nan or inf in z, u or y at step 2: p unchanged, each refusal counted, no numpy
    warning. The last refused sample's z_2 is finite, so with steps 3 and 4 the estimate has
    taken the residuals of steps 1, 3 and 4 of a constant w: p = (1 - 0.5^3) [w; 0]."""
    model = biased_oscillator()
    est = DisturbanceEstimator(model, disturbance_model(model, 'state'), gain=0.5)
    x, u, w = np.array([0.2, -0.1]), np.array([0.4]), np.array([0.1, -0.05])
    xs = [x]
    for _ in range(4):
        xs.append(model.step(xs[-1], u) + w)
    bad = ((np.array([np.inf, 0.0]), u, model.output(xs[2])),
           (xs[2], np.array([np.nan]), model.output(xs[2])),
           (xs[2], u, np.array([-np.inf, np.inf])))
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        for t in (0, 1):
            est.update(xs[t], u, model.output(xs[t]), step=t)
        p = est.p.copy()
        for k, (z, u_bad, y) in enumerate(bad, start=1):
            est.update(z, u_bad, y, step=2)
            assert est.refused == k and np.all(est.p == p)
        for t in (3, 4):
            est.update(xs[t], u, model.output(xs[t]), step=t)
    assert est.refused == 3
    assert est.p == pytest.approx(np.r_[(1 - 0.5 ** 3) * w, 0.0, 0.0], abs=1e-12)


def test_a_non_finite_measurement_or_reference_fails_the_tick_and_nothing_else():
    """Offset-free MPC: a nan y_t is refused by the estimator and the tick falls back
    ('invalid data', the shifted plan, the estimate unchanged) as for a nan z_t; an inf
    reference never reaches the steady-state target (no numpy warning); the next finite tick
    solves."""
    model = oscillator()
    mpc = LatentMpc(MpcConfig(horizon=10, q=(1.0, 0.0), u_min=-1.0, u_max=1.0,
                              offset_free='state'))
    mpc.set_model(model)
    ref = np.tile([0.5, 0.0], (10, 1))
    x, u = np.array([0.1, 0.0]), np.zeros(1)
    first = mpc.solve(x, u, ref, model.output(x), 0)
    assert not first.fallback
    x = model.step(x, first.u) + 0.05
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        nan_y = mpc.solve(x, first.u, ref, np.array([np.nan, 0.0]), 1)
        inf_ref = mpc.solve(x, first.u, np.full((10, 2), np.inf), model.output(x), 1)
    for res in (nan_y, inf_ref):
        assert res.fallback and res.status == 'invalid data'
        assert np.all(np.isfinite(res.u_plan)) and np.all(np.isfinite(res.disturbance))
    np.testing.assert_array_equal(nan_y.disturbance, first.disturbance)
    assert mpc._problem.estimator.refused == 1
    x = model.step(x, inf_ref.u)
    after = mpc.solve(x, inf_ref.u, ref, model.output(x), 2)
    assert not after.fallback and after.status == 'solved'
