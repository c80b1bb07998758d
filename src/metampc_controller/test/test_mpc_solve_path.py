"""LatentMpc.solve's lean path (docs/mpc.md, Speed of the tick): the compiled OSQP call against
a second osqp.OSQP driven through its public API with the same data, bit for bit; its q against
-2 M'v of a least-squares form built by simulating the model (not from mpc.py's matrices). (The
numpy encoder's test is the model's test_predictor.py; the history's is in
test_controller_core.py.)
"""
from dataclasses import replace

import numpy as np
import osqp
import pytest

from metampc_controller import mpc as mpc_module
from metampc_model.latent_model import LatentModel
from metampc_controller.mpc import LatentMpc, MpcConfig
from metampc_controller.references import make_reference


def random_model(seed: int, radius: float = 0.95, n_z: int = 5) -> LatentModel:
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n_z, n_z))
    a *= radius / max(abs(np.linalg.eigvals(a)))
    return LatentModel(A=a, B=rng.normal(size=(n_z, 1)), C=rng.normal(size=(2, n_z)),
                       e=0.1 * rng.normal(size=n_z), d=0.1 * rng.normal(size=2))


# --- the QP solve --------------------------------------------------------------------------

def steady_state(model: LatentModel, y1: float) -> np.ndarray:
    """[z; u] with z = A z + B u + e and y_1 = y1 (one input, one tracked output)."""
    n_z = model.n_z
    mat = np.block([[model.A - np.eye(n_z), model.B], [model.C[:1], np.zeros((1, 1))]])
    return np.linalg.solve(mat, np.concatenate([-model.e, [y1 - model.d[0]]]))


def simulated_lsq(model: LatentModel, cfg: MpcConfig, p_term, z0, u_prev, y_ref) -> tuple:
    """(M, v) with J(U) = ||M U - v||^2, from simulations of the model input by input and eq.
    (mpc) as written (Q on y_{1..N-1}, (s_N - s_ss)' P (s_N - s_ss) with the steady state
    solved here, R on du_{0..N-1}), independent of mpc.py's condensed matrices."""
    n, q, r = cfg.horizon, np.asarray(cfg.q), float(cfg.r[0])
    chol = np.linalg.cholesky(p_term).T

    def residual(plan: np.ndarray) -> np.ndarray:
        z, ys = np.array(z0, dtype=float), []
        for u in plan:
            z = model.step(z, np.array([u]))
            ys.append(model.output(z))
        ys = np.array(ys)
        s_n = np.concatenate([z, plan[-1:]])
        return np.concatenate([
            (np.sqrt(q) * (ys[:-1] - y_ref[:-1])).ravel(),
            chol @ (s_n - steady_state(model, y_ref[-1, 0])),
            np.sqrt(r) * np.diff(np.concatenate([u_prev, plan]))])

    base = residual(np.zeros(n))
    return np.column_stack([residual(np.eye(n)[j]) - base for j in range(n)]), -base


def osqp_like(mpc: LatentMpc) -> osqp.OSQP:
    """A second OSQP set up as LatentMpc sets up its own (q = 0, same settings)."""
    qp = mpc.last_qp()
    solver = osqp.OSQP()
    solver.setup(P=qp.P, q=np.zeros(qp.P.shape[0]), A=qp.A, l=qp.l, u=qp.u,
                 **mpc.config.osqp_settings())
    return solver


def test_solve_is_a_second_osqp_on_the_same_qp_and_q_is_the_simulated_one():
    model = random_model(3)
    cfg = MpcConfig(horizon=20, time_limit=30.0)
    mpc = LatentMpc(cfg)
    mpc.set_model(model)
    assert mpc._problem.ext is not None, 'the osqp wrapper changed: solve() lost its fast path'
    assert not mpc.terminal.dare_unusable
    reference = make_reference('setpoint_sequence', segment=3.0)
    second = None
    z, u = np.zeros(5), np.zeros(1)
    for k in range(150):
        if k == 80:                       # a new episode: both start cold
            mpc.reset()
            second = None
        y_ref = reference.evaluate(k * 0.1, 0.1, cfg.horizon)
        res = mpc.solve(z, u, y_ref)
        qp = mpc.last_qp()
        if second is None:
            second = osqp_like(mpc)
        # q against the least-squares form built by simulation: q = -2 M'v.
        mat, vec = simulated_lsq(model, cfg, mpc.terminal.P, z, u, y_ref)
        q_sim = -2.0 * mat.T @ vec
        assert np.abs(qp.q - q_sim).max() <= 1e-9 * max(1.0, np.abs(q_sim).max())
        # The same QP through the wrapper's public calls: the same iterates, the same bits.
        second.update(q=qp.q)
        if qp.x_warm is not None:
            second.warm_start(x=qp.x_warm)
        ref = second.solve(raise_error=False)
        assert (res.status, res.iterations, res.fallback) == (ref.info.status, ref.info.iter,
                                                              False)
        np.testing.assert_array_equal(res.u_plan[:, 0], np.clip(ref.x, -1.0, 1.0))
        # Its cost is J at OSQP's answer, ||M x - v||^2 of the simulated form.
        assert res.cost == pytest.approx(np.sum((mat @ ref.x - vec) ** 2), rel=1e-8, abs=1e-12)
        np.testing.assert_allclose(
            res.y_pred, [model.output(zk) for zk in rollout(model, z, res.u_plan)], atol=1e-10)
        u = res.u
        z = model.step(z, u)


def rollout(model: LatentModel, z0: np.ndarray, plan: np.ndarray) -> list:
    zs, z = [], z0
    for u in plan:
        z = model.step(z, u)
        zs.append(z)
    return zs


def test_the_compiled_path_and_the_wrapper_path_give_the_same_bits(monkeypatch):
    """solve() through the wrapper's public calls (as before the lean tick, and where an
    osqp without the compiled object is installed) and through the compiled solver."""
    model = random_model(5)
    cfg = MpcConfig(horizon=10, u_min=-0.5, u_max=0.5, time_limit=30.0)
    fast = LatentMpc(cfg)
    fast.set_model(model)
    with monkeypatch.context() as patch:
        patch.setattr(mpc_module, '_extension', lambda solver: None)
        plain = LatentMpc(cfg)
        plain.set_model(model)
        assert plain._problem.ext is None and fast._problem.ext is not None
        reference = make_reference('steps', steps=[(0.0, 0.7), (2.0, -0.4)])
        z, u = np.ones(5), np.zeros(1)
        for k in range(120):
            if k == 60:
                for m in (fast, plain):
                    m.reset()
            z_k = np.full(5, np.nan) if k in (30, 31) else z      # invalid data: fallback
            if k == 90:                                              # capped: fallback
                for m in (fast, plain):
                    m.set_config(replace(cfg, max_iter=1, warm_start=False))
            a = fast.solve(z_k, u, reference.evaluate(k * 0.1, 0.1, 10))
            b = plain.solve(z_k, u, reference.evaluate(k * 0.1, 0.1, 10))
            for name in ('u', 'u_plan', 'y_pred'):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
            assert (a.status, a.iterations, a.fallback) == (b.status, b.iterations, b.fallback)
            assert a.cost == b.cost or (np.isnan(a.cost) and np.isnan(b.cost))
            assert a.fallback == (k in (30, 31) or k >= 90)
            u = a.u
            z = model.step(z, u)
