"""The latent MPC core, checked against answers obtained independently of its QP construction.

The reference answers rebuild eq. (mpc) by simulating the LatentModel input by input (not
from the condensed matrices of mpc.py) and solve it with scipy's bounded least squares, the
normal equations or the steady-state equations written out by hand.
"""
from dataclasses import replace

import numpy as np
import pytest
from scipy.linalg import expm, solve_discrete_are
from scipy.optimize import lsq_linear

from metampc_model.latent_model import LatentModel
from metampc_controller.mpc import LatentMpc, MpcConfig
from metampc_controller.references import make_reference

# OSQP tightened so that its answer is comparable with a direct least-squares solver.
TIGHT = dict(eps_abs=1e-10, eps_rel=1e-10, polish=True, max_iter=200000, time_limit=30.0)


def random_model(seed: int, radius: float, n_z: int = 5) -> LatentModel:
    """Random affine latent model (n_y = 2, n_u = 1) with spectral radius `radius`."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n_z, n_z))
    a *= radius / max(abs(np.linalg.eigvals(a)))
    return LatentModel(A=a, B=rng.normal(size=(n_z, 1)), C=rng.normal(size=(2, n_z)),
                       e=0.1 * rng.normal(size=n_z), d=0.1 * rng.normal(size=2))


def non_stabilisable_model() -> LatentModel:
    """The first latent mode is unstable (1.2) and no input reaches it."""
    a = np.diag([1.2, 0.5, 0.3, -0.2, 0.1])
    b = np.array([[0.0], [1.0], [1.0], [1.0], [1.0]])
    c = np.array([[0.5, 1.0, 0.0, 1.0, 0.0], [0.0, 0.0, 1.0, 0.0, 1.0]])
    return LatentModel(A=a, B=b, C=c, e=np.zeros(5), d=np.zeros(2))


def oscillator(dt: float = 0.1, omega: float = 1.0, zeta: float = 0.5) -> LatentModel:
    """x1'' + 2 zeta omega x1' + omega^2 x1 = omega^2 u, zero-order hold at dt; y = x, so a
    set-point x1 = v needs u = v."""
    a_c = np.array([[0.0, 1.0], [-omega ** 2, -2.0 * zeta * omega]])
    b_c = np.array([[0.0], [omega ** 2]])
    m = expm(np.block([[a_c, b_c], [np.zeros((1, 3))]]) * dt)
    return LatentModel(A=m[:2, :2], B=m[:2, 2:], C=np.eye(2), e=np.zeros(2), d=np.zeros(2))


def simulate(model: LatentModel, z0: np.ndarray, plan: np.ndarray) -> tuple:
    """Outputs y_{1..N} (N, n_y) and the last latent state z_N under inputs plan (N, n_u)."""
    z, ys = np.array(z0, dtype=float), []
    for u in plan:
        z = model.step(z, u)
        ys.append(model.output(z))
    return np.array(ys), z


def steady_state(model: LatentModel, y1: float) -> np.ndarray:
    """[z; u] with z = A z + B u + e and y_1 = y1 (square: one input, one tracked output)."""
    n_z = model.n_z
    mat = np.block([[model.A - np.eye(n_z), model.B], [model.C[:1], np.zeros((1, 1))]])
    return np.linalg.solve(mat, np.concatenate([-model.e, [y1 - model.d[0]]]))


def reference_lsq(mpc: LatentMpc, model: LatentModel, z0, u_prev, y_ref) -> tuple:
    """(M, v) with J(U) = ||M U - v||^2, from simulations of the model and eq. (mpc) as
    written: Q on y_{1..N-1}, the terminal term, R on du_{0..N-1}."""
    cfg = mpc.config
    n = cfg.horizon
    q, r = np.asarray(cfg.q), float(cfg.r)
    term = mpc.terminal

    def residual(plan: np.ndarray) -> np.ndarray:
        ys, z_n = simulate(model, z0, plan[:, None])
        rows = [(np.sqrt(q) * (ys[:-1] - y_ref[:-1])).ravel()]
        if term.dare_unusable:
            rows.append(np.sqrt(q) * (ys[-1] - y_ref[-1]))
        else:
            s_n = np.concatenate([z_n, plan[-1:]])
            rows.append(np.linalg.cholesky(term.P).T @ (s_n - steady_state(model, y_ref[-1, 0])))
        rows.append(np.sqrt(r) * np.diff(np.concatenate([u_prev, plan])))
        return np.concatenate(rows)

    # The residual is affine in U: its columns are the responses to unit inputs.
    base = residual(np.zeros(n))
    mat = np.column_stack([residual(np.eye(n)[j]) - base for j in range(n)])
    return mat, -base


@pytest.mark.parametrize('seed,radius,model_kind', [
    (0, 0.9, 'random'), (1, 0.9, 'random'), (2, 1.1, 'random'), (3, 1.15, 'random'),
    (4, 1.0, 'non-stabilisable')])
def test_qp_is_bounded_least_squares(seed, radius, model_kind):
    model = random_model(seed, radius) if model_kind == 'random' else non_stabilisable_model()
    rng = np.random.default_rng(100 + seed)
    n = 15
    z0, u_prev = rng.normal(size=5), np.array([0.2])
    y_ref = np.zeros((n, 2))
    y_ref[:, 0] = 0.5 + 0.3 * np.sin(np.arange(n) / 3.0)
    y_ref[:, 1] = rng.normal(size=n)        # untracked (q = 0): must not matter
    base = MpcConfig(horizon=n, q=(1.0, 0.0), r=0.05, **TIGHT)

    # Unconstrained: the normal equations.
    mpc = LatentMpc(replace(base, u_min=-np.inf, u_max=np.inf))
    mpc.set_model(model)
    assert mpc.terminal.dare_unusable == (model_kind == 'non-stabilisable')
    res = mpc.solve(z0, u_prev, y_ref)
    mat, vec = reference_lsq(mpc, model, z0, u_prev, y_ref)
    expected = np.linalg.solve(mat.T @ mat, mat.T @ vec)
    assert res.status == 'solved' and not res.fallback
    np.testing.assert_allclose(res.u_plan[:, 0], expected, atol=1e-4, rtol=0)

    # Bounds that cut some inputs of the optimum, not all.
    bound = 0.4 * np.max(np.abs(expected))
    mpc = LatentMpc(replace(base, u_min=-bound, u_max=bound))
    mpc.set_model(model)
    res = mpc.solve(z0, u_prev, y_ref)
    expected = lsq_linear(mat, vec, bounds=(-bound, bound), method='bvls', tol=1e-14).x
    assert 2 <= np.sum(np.isclose(np.abs(expected), bound)) <= n - 2
    assert res.status == 'solved' and not res.fallback
    np.testing.assert_allclose(res.u_plan[:, 0], expected, atol=1e-4, rtol=0)
    assert np.all(np.abs(res.u_plan) <= bound)
    # Reported cost and prediction are those of the plan.
    plan = res.u_plan[:, 0]
    assert res.cost == pytest.approx(np.sum((mat @ plan - vec) ** 2), rel=1e-6)
    np.testing.assert_allclose(res.y_pred, simulate(model, z0, res.u_plan)[0], atol=1e-9)
    np.testing.assert_array_equal(res.u, res.u_plan[0])


def dare_residual(a, b, q, r, p) -> float:
    """Relative residual of P = A'PA - A'PB (R + B'PB)^{-1} B'PA + Q, written out."""
    k = np.linalg.inv(r + b.T @ p @ b) @ b.T @ p @ a
    return np.linalg.norm(a.T @ p @ a - a.T @ p @ b @ k + q - p) / np.linalg.norm(p)


@pytest.mark.parametrize('seed,radius', [(0, 0.5), (1, 0.95), (2, 1.05), (3, 1.3)])
def test_terminal_weight_solves_the_dare(seed, radius):
    model = random_model(seed, radius)
    cfg = MpcConfig(horizon=10)
    mpc = LatentMpc(cfg)
    mpc.set_model(model)
    term = mpc.terminal
    assert not term.dare_unusable and term.reason == ''
    # The augmented Delta-u system and its weights, written out here.
    n_z = model.n_z
    a = np.block([[model.A, model.B], [np.zeros((1, n_z)), np.eye(1)]])
    b = np.vstack([model.B, np.eye(1)])
    c = np.hstack([model.C, np.zeros((2, 1))])
    q_out = c.T @ np.diag(cfg.q) @ c
    q_bar = q_out + cfg.terminal_reg * np.linalg.norm(q_out, 2) * np.eye(n_z + 1)
    r = np.diag(np.atleast_1d(cfg.r))
    assert dare_residual(a, b, q_bar, r, term.P) <= 1e-8
    assert term.residual <= 1e-8
    np.testing.assert_allclose(term.P, term.P.T, atol=0)
    assert np.linalg.eigvalsh(term.P)[0] > 0
    gain = np.linalg.solve(r + b.T @ term.P @ b, b.T @ term.P @ a)
    assert max(abs(np.linalg.eigvals(a - b @ gain))) < 1.0


def perturbed(model: LatentModel, seed: int, size: float) -> LatentModel:
    """The model with A and B moved by `size` (relative, random): a relinearisation's next."""
    rng = np.random.default_rng(seed)
    return replace(model, A=model.A * (1 + size * rng.normal(size=model.A.shape)),
                   B=model.B * (1 + size * rng.normal(size=model.B.shape)))


@pytest.mark.parametrize('seed,radius', [(0, 0.5), (1, 0.95), (2, 1.05), (3, 1.3)])
def test_the_dare_is_scipys_stabilising_solution(seed, radius):
    """terminal_cost.dare (QZ of the reciprocal symplectic pencil, LAPACK directly) against
    scipy's solve_discrete_are (QZ of the extended pencil, balanced) on the augmented system
    (fails where the subspace of the eigenvalues outside the unit circle is taken, or R^{-1}
    is left out of B R^{-1} B'); a pair with an unstable mode no input reaches has none."""
    from metampc_controller.terminal_cost import augmented, dare
    # The NARX's P has a condition number 1e11-6e13: the two QZ methods agree to 5e-8 there.
    for model, reg, tol in ((random_model(seed, radius), 1e-8, 1e-10),
                            (perturbed(model_narx(), seed, 0.01), 1e-6, 1e-6)):
        ab, c = augmented(model)
        n_s = model.n_z + model.n_u
        a, b = ab[:, :n_s], ab[:, n_s:]
        q_out = c.T @ np.diag([1.0, 0.0]) @ c
        q = q_out + reg * np.linalg.norm(q_out, 2) * np.eye(n_s)
        r = np.array([0.05])
        p, expected = dare(a, b, q, r), solve_discrete_are(a, b, q, np.diag(r))
        np.testing.assert_allclose(p, expected, rtol=0, atol=tol * np.abs(expected).max())
        assert dare_residual(a, b, q, np.diag(r), p) <= 1e-7
    ab, c = augmented(non_stabilisable_model())
    with pytest.raises(np.linalg.LinAlgError):     # U1 singular: no stabilising P
        dare(ab[:, :6], ab[:, 6:], c.T @ c + 1e-6 * np.eye(6), np.array([0.05]))


def model_narx() -> LatentModel:
    """A feature NARX's linearisation as the locally linear MPC plans on it (order 2, seeded
    features fitted to van der Pol at theta* 1.5, entries rounded): z = [y_t; y_{t-1}; u_t],
    an unstable pair (|1.07|), a singular A (the input lag); its DARE solution (with the
    Delta-u form's integrator) has a condition number ~2e11."""
    a = np.zeros((5, 5))
    a[:2] = [[-3.78, 0.384, 4.78, 0.196, -0.004], [-111.857, 7.429, 111.85, 4.805, -0.057]]
    a[2:4, :2] = np.eye(2)
    b = np.zeros((5, 1))
    b[:2, 0], b[4, 0] = [0.005, 0.093], 1.0
    c = np.hstack([np.eye(2), np.zeros((2, 3))])
    return LatentModel(A=a, B=b, C=c, e=np.array([0.0, 0.01, 0.0, 0.0, 0.0]), d=np.zeros(2))


@pytest.mark.parametrize('start', ['stable', 'unstable', 'narx'])
def test_a_near_model_sets_up_the_qp_a_new_one_does(start):
    """set_model(near=True) on a sequence of relinearisations (the OSQP instance and the
    problem in use updated in place, the DARE's state weight kept) against a fresh LatentMpc
    set up on each model, and against the reference least squares of the model's own
    simulation, with bounds that cut the optimum: the same QP, the same plan to OSQP's
    tolerance. Then a model whose DARE is unusable (the terminal form changes size), and back.
    Fails where the update in place keeps the previous H, the terminal rows or steady state
    of the previous model stay (a stale terminal block), or a du row is off by one step."""
    model = {'stable': random_model(4, 0.9), 'unstable': random_model(5, 1.3),
             'narx': model_narx()}[start]
    n = 12
    # offset_free none, as LocalLinearMpc plans: the terminal cost centred on the unbounded
    # steady state, as the reference's is.
    cfg = replace(MpcConfig(horizon=n, q=(1.0, 0.0), r=0.05, u_min=-0.3, u_max=0.3,
                            offset_free='none'), **TIGHT)
    reused = LatentMpc(cfg)
    reused.set_model(model)
    z0, u_prev = np.array([0.6, -0.3, 0.5, 0.2, 0.1]), np.array([0.1])
    ref = np.zeros((n, 2))
    ref[:, 0] = 0.8
    reused.solve(z0, u_prev, ref)
    sequence = [perturbed(model, 10 + k, 0.05) for k in range(3)]
    for model in sequence + [non_stabilisable_model(), sequence[-1]]:
        reused.set_model(model, near=True)
        fresh = LatentMpc(cfg)
        fresh.set_model(model)
        a, b = reused.solve(z0, u_prev, ref), fresh.solve(z0, u_prev, ref)
        assert reused.terminal.dare_unusable == fresh.terminal.dare_unusable
        qa, qb = reused.last_qp(), fresh.last_qp()
        np.testing.assert_allclose(qa.P.toarray(), qb.P.toarray(), rtol=1e-9,
                                   atol=1e-9 * np.abs(qb.P).max())
        np.testing.assert_allclose(qa.q, qb.q, rtol=1e-9, atol=1e-9 * np.abs(qb.q).max())
        np.testing.assert_allclose(a.u_plan, b.u_plan, atol=1e-7)
        mat, vec = reference_lsq(reused, model, z0, u_prev, ref)
        expected = lsq_linear(mat, vec, bounds=(-0.3, 0.3), method='bvls', tol=1e-14).x
        assert np.sum(np.isclose(np.abs(expected), 0.3)) >= 1        # the bounds are active
        np.testing.assert_allclose(a.u_plan[:, 0], expected, atol=1e-5)
    # Another size (n_z 5 -> 3): a new QP, solved as a fresh one is.
    small = random_model(5, 0.8, n_z=3)
    reused.set_model(small, near=True)
    fresh = LatentMpc(cfg)
    fresh.set_model(small)
    np.testing.assert_allclose(reused.solve(np.zeros(3), np.zeros(1), ref).u_plan,
                               fresh.solve(np.zeros(3), np.zeros(1), ref).u_plan, atol=1e-7)


def test_non_stabilisable_pair_falls_back_to_the_output_weight():
    model = non_stabilisable_model()
    cfg = MpcConfig(horizon=10)
    mpc = LatentMpc(cfg)
    mpc.set_model(model)
    term = mpc.terminal
    assert term.dare_unusable and term.reason
    c = np.hstack([model.C, np.zeros((2, 1))])
    np.testing.assert_allclose(term.P, c.T @ np.diag(cfg.q) @ c)
    z, u = np.array([1.0, 0.5, -0.5, 0.2, 0.0]), np.zeros(1)
    for k in range(30):
        res = mpc.solve(z, u, np.tile([0.3, 0.0], (10, 1)))
        assert res.terminal_fallback and not res.fallback
        assert np.all(np.isfinite(res.u_plan)) and np.all(np.abs(res.u_plan) <= 1.0)
        u = res.u
        z = model.step(z, u)


def total_variation(u: np.ndarray) -> float:
    return float(np.sum(np.abs(np.diff(u))))


def closed_loop(model: LatentModel, cfg: MpcConfig, reference, ticks: int,
                dt: float = 0.1) -> tuple:
    """Receding horizon on the model itself: (outputs (ticks, n_y), inputs (ticks,), results)."""
    mpc = LatentMpc(cfg)
    mpc.set_model(model)
    z, u = np.zeros(model.n_z), np.zeros(model.n_u)
    ys, us, results = [], [], []
    for k in range(ticks):
        res = mpc.solve(z, u, reference.evaluate(k * dt, dt, cfg.horizon))
        u = res.u
        z = model.step(z, u)
        ys.append(model.output(z))
        us.append(u[0])
        results.append(res)
    return np.array(ys), np.array(us), results


def test_closed_loop_reaches_set_points_within_bounds():
    model = oscillator()
    steps = make_reference('steps', steps=[(0.0, 0.9), (20.0, -0.4)])
    cfg = MpcConfig(horizon=20, q=(1.0, 0.0), r=0.05, time_limit=1.0)
    ys, us, results = closed_loop(model, cfg, steps, 400)
    assert not any(r.fallback for r in results)
    assert np.all(np.abs(us) <= 1.0)
    assert np.max(np.abs(us)) == 1.0          # the step to 0.9 saturates the input
    # Zero steady-state error (the model is exact): before the MPC starts anticipating the next
    # step (a horizon, 2 s, ahead) and at the end; the input settles at u_ss = set-point.
    assert abs(ys[175, 0] - 0.9) < 1e-5 and abs(ys[-1, 0] + 0.4) < 1e-5
    assert abs(us[175] - 0.9) < 1e-4 and abs(us[-1] + 0.4) < 1e-4


def test_larger_delta_u_weight_gives_smoother_inputs():
    model = oscillator()
    steps = make_reference('steps', steps=[(0.0, 0.5), (5.0, -0.5), (10.0, 0.2)])
    tv = {}
    for r in (0.01, 0.1, 1.0):
        cfg = MpcConfig(horizon=20, r=r, time_limit=1.0)
        _, us, _ = closed_loop(model, cfg, steps, 150)
        assert np.all(np.abs(us) <= 1.0)
        tv[r] = total_variation(us)
    # Measured 14.1, 10.3, 6.8.
    assert tv[0.01] > 1.2 * tv[0.1] and tv[0.1] > 1.2 * tv[1.0]


def test_warm_start_lowers_iterations():
    model = random_model(7, 0.95)
    paper = make_reference('setpoint_sequence', segment=3.0)
    iters = {}
    for warm in (True, False):
        cfg = MpcConfig(horizon=20, warm_start=warm, time_limit=1.0)
        _, _, results = closed_loop(model, cfg, paper, 120)
        assert not any(r.fallback for r in results)
        iters[warm] = np.mean([r.iterations for r in results])
    assert iters[True] < 0.7 * iters[False]


def shifted(plan: np.ndarray) -> np.ndarray:
    return np.vstack([plan[1:], plan[-1:]])


def test_failures_return_the_shifted_previous_plan():
    model = random_model(8, 0.9)
    cfg = MpcConfig(horizon=10, u_min=-0.5, u_max=0.5, time_limit=1.0)
    mpc = LatentMpc(cfg)
    mpc.set_model(model)
    y_ref = np.tile([0.7, 0.0], (10, 1))
    z, u = np.ones(5), np.zeros(1)
    good = mpc.solve(z, u, y_ref)
    assert not good.fallback and len(np.unique(good.u_plan)) > 2

    # Non-finite latent state: no solve, the shifted plan, twice in a row.
    bad = mpc.solve(np.full(5, np.nan), good.u, y_ref)
    assert bad.fallback and bad.status == 'invalid data' and bad.iterations == 0
    assert np.isnan(bad.cost) and np.all(np.isnan(bad.y_pred))
    np.testing.assert_array_equal(bad.u_plan, shifted(good.u_plan))
    again = mpc.solve(z, good.u, np.full((10, 2), np.inf))
    assert again.fallback
    np.testing.assert_array_equal(again.u_plan, shifted(shifted(good.u_plan)))

    # Capped solver: one iteration cannot solve it.
    good = mpc.solve(z, u, y_ref)
    mpc.set_config(replace(cfg, max_iter=1, warm_start=False))
    capped = mpc.solve(2.0 * z, good.u, y_ref)
    assert capped.fallback and capped.status == 'maximum iterations reached'
    np.testing.assert_array_equal(capped.u_plan, shifted(good.u_plan))
    for res in (bad, again, capped):
        assert np.all(np.isfinite(res.u_plan)) and np.all(np.abs(res.u_plan) <= 0.5)
        assert np.all(np.isfinite(res.u)) and res.u.shape == (1,)


@pytest.mark.parametrize('settings', [dict(max_iter=1, warm_start=False), dict(time_limit=1e-9)])
def test_failure_before_any_plan_holds_the_previous_input_clipped(settings):
    mpc = LatentMpc(MpcConfig(horizon=10, **settings))
    mpc.set_model(random_model(9, 0.9))
    y_ref = np.tile([0.7, 0.0], (10, 1))
    res = mpc.solve(np.ones(5), np.array([5.0]), y_ref)
    assert res.fallback and res.status != 'solved'
    np.testing.assert_array_equal(res.u_plan, np.ones((10, 1)))
    mpc.reset()
    res = mpc.solve(np.ones(5), np.array([np.nan]), y_ref)     # nothing to hold: 0, clipped
    np.testing.assert_array_equal(res.u_plan, np.zeros((10, 1)))


def test_invalid_settings_and_shapes_are_rejected():
    for bad in (dict(r=0.0), dict(u_min=1.0, u_max=-1.0), dict(q=(1.0, -1.0)), dict(horizon=0),
                dict(time_limit=0.0)):
        with pytest.raises(ValueError):
            MpcConfig(**bad)
    mpc = LatentMpc(MpcConfig(horizon=5, q=(1.0, 0.0, 0.0)))
    with pytest.raises(ValueError):
        mpc.set_model(random_model(0, 0.9))     # 3 weights, 2 outputs
    with pytest.raises(RuntimeError):
        mpc.solve(np.zeros(5), np.zeros(1), np.zeros((5, 2)))
    mpc = LatentMpc(MpcConfig(horizon=5))
    mpc.set_model(random_model(0, 0.9))
    with pytest.raises(ValueError):
        mpc.solve(np.zeros(5), np.zeros(1), np.zeros((2, 5)))


@pytest.mark.parametrize('fast', [True, False])
def test_a_sigint_during_a_solve_reaches_the_process_handler(fast):
    """OSQP's Ctrl-C listener takes a SIGINT that lands during a solve; solve() gives it back,
    so the process's handler (a node's stop request) sees it. A thread sends 20 SIGINTs, each
    once the handler counted the one before (or 5 s passed), while the main thread solves a
    long-horizon QP back to back (most of the time inside OSQP). Measured: without the give-back
    3 of 20 were counted; with it 19-20: OSQP checks its flag at the start of each iteration,
    so a signal landing in the last one (about 1 in 40 here) is still lost. At least 15 of 20
    (a loss of 6 at 1 in 40 has odds ~1e-6)."""
    import signal
    import threading
    import time
    model = random_model(3, 0.95)
    cfg = MpcConfig(horizon=150, time_limit=1.0, eps_abs=1e-9, eps_rel=1e-9, max_iter=4000)
    mpc = LatentMpc(cfg)
    mpc.set_model(model)
    if not fast:
        mpc._problem.ext = None          # the osqp.OSQP wrapper's solve()
    ref = np.tile([0.5, 0.0], (150, 1))
    counted, sent, done = [], [], threading.Event()

    def sender():
        main = threading.main_thread().ident
        for _ in range(20):
            before = len(counted)
            sent.append(time.monotonic())
            signal.pthread_kill(main, signal.SIGINT)
            deadline = time.monotonic() + 5.0
            while len(counted) == before and time.monotonic() < deadline:
                time.sleep(0.001)
        done.set()

    previous = signal.signal(signal.SIGINT, lambda *_: counted.append(1))
    try:
        thread = threading.Thread(target=sender)
        thread.start()
        z, u = np.zeros(model.n_z), np.zeros(1)
        while not done.is_set():
            z = 0.9 * model.step(z, mpc.solve(z, u, ref).u)
        thread.join()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert len(sent) == 20 and len(counted) >= 15, f'{len(counted)} of 20 counted'
