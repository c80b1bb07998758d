"""Meta-gradients of eq. (meta_gradient) against independent dense / autograd / finite-difference
computations: iMAML's (imaml.py, with cg.py and both curvatures of curvature.py) and MAML's
(maml.py), all on one small problem, whose dense reference is the point of this file.

Small NSSM in float64 so that dense Hessians and Jacobians are cheap and exact.
"""
import numpy as np
import pytest
import torch
from torch.autograd.functional import hessian, jacobian

from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.curvature import gauss_newton_product, hessian_product
from metampc_learner.data import normalisation_from, simulate_source, SourceConfig, SourceSet
from metampc_learner.imaml import ImamlTaskGradient
from metampc_learner.maml import FirstOrderMamlTaskGradient, UnrolledMamlTaskGradient
from metampc_learner.meta_train import batch_gradient_fn, MetaConfig
from metampc_learner.objective import FlatObjective

torch.set_num_threads(1)
F64 = torch.float64
SMALL = NssmConfig(history=3, loss_horizon=4, hidden=(16,), n_z=3)
GAMMA = 5.0       # makes I + H/gamma positive definite here (checked) and the inner problem
LR = 0.05         # strongly convex, so that
CONVERGED = 200   # inner steps solve it to ~1e-12


@pytest.fixture(scope='module')
def problem():
    data = simulate_source(SourceConfig(n_systems=3, episodes_per_system=1, episode_samples=60,
                                        seed=2))
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    model = Nssm(SMALL, norm, dtype=F64)
    source = SourceSet(data, norm, SMALL, dtype=F64)
    train, test = source.sample([0, 1, 2], 12, np.random.default_rng(0))
    objective = FlatObjective(model)
    omega = objective.spec.flatten(init_params(SMALL, 1, F64))
    return objective, omega, train, test


def _dense_hessian(objective, psi, u, y):
    return hessian(lambda p: objective.loss(p, u, y), psi)


def _cos_rel(a, b):
    return float(a @ b / (a.norm() * b.norm())), float((a - b).norm() / b.norm())


def _prox_grad_norm(objective, psi, omega, u, y):
    return float((torch.func.grad(objective.loss)(psi, u, y) + GAMMA * (psi - omega)).norm())


@pytest.mark.parametrize('curvature', ['hessian', 'gauss_newton'])
def test_cg_meta_gradient_matches_dense_implicit_gradient(problem, curvature):
    objective, omega, train, test = problem
    tr_u, tr_y, te_u, te_y = train.u[0], train.y[0], test.u[0], test.y[0]
    task = ImamlTaskGradient(objective, CONVERGED, LR, GAMMA, cg_steps=60, curvature=curvature)
    out = task(omega, tr_u, tr_y, te_u, te_y)
    psi = out.adapted
    assert _prox_grad_norm(objective, psi, omega, tr_u, tr_y) < 1e-9, 'inner not converged'
    if curvature == 'hessian':
        curv = _dense_hessian(objective, psi, tr_u, tr_y)
    else:
        jac = jacobian(lambda p: objective.predict(p, tr_u, tr_y), psi).reshape(-1, psi.numel())
        curv = 2.0 / objective.n_terms(tr_u) * jac.T @ jac
    q = torch.eye(psi.numel(), dtype=F64) + curv / GAMMA
    assert torch.linalg.eigvalsh(q).min() > 0.05, 'I + H/gamma must be positive definite here'
    p_b = torch.func.grad(objective.loss)(psi, te_u, te_y)
    exact = torch.linalg.solve(q, p_b)
    cos, rel = _cos_rel(out.grad, exact)
    assert cos >= 0.999 and rel <= 1e-3, (cos, rel)
    assert float(out.cg_residual) < 1e-6
    assert torch.allclose(out.test_loss, objective.loss(psi, te_u, te_y))


def test_exact_meta_gradient_matches_finite_differences_of_the_solved_bilevel_problem(problem):
    """d/d omega l(D_test; omega_b(omega)) by central differences, re-solving the inner problem."""
    objective, omega, train, test = problem
    tr_u, tr_y, te_u, te_y = train.u[1], train.y[1], test.u[1], test.y[1]
    task = ImamlTaskGradient(objective, CONVERGED, LR, GAMMA, cg_steps=80, curvature='hessian')
    meta_grad = task(omega, tr_u, tr_y, te_u, te_y).grad

    def outer(w):
        psi = objective.inner_loop(w, tr_u, tr_y, CONVERGED, LR, GAMMA)
        return float(objective.loss(psi, te_u, te_y))

    gen = torch.Generator().manual_seed(0)
    eps = 1e-5
    for _ in range(2):
        v = torch.randn(omega.shape, generator=gen, dtype=F64)
        v /= v.norm()
        fd = (outer(omega + eps * v) - outer(omega - eps * v)) / (2 * eps)
        assert abs(fd - float(meta_grad @ v)) <= 1e-5 * max(1.0, abs(fd)), (fd, meta_grad @ v)


def test_curvature_products_equal_dense_products(problem):
    objective, omega, train, _ = problem
    u, y = train.u[2], train.y[2]
    psi = omega + 0.01 * torch.randn(omega.shape, generator=torch.Generator().manual_seed(3),
                                     dtype=F64)
    v = torch.randn(omega.shape, generator=torch.Generator().manual_seed(4), dtype=F64)
    jac = jacobian(lambda p: objective.predict(p, u, y), psi).reshape(-1, psi.numel())
    dense_gn = 2.0 / objective.n_terms(u) * (jac.T @ (jac @ v))
    assert torch.allclose(gauss_newton_product(objective, psi, u, y)(v), dense_gn,
                          rtol=1e-10, atol=1e-12)
    dense_h = _dense_hessian(objective, psi, u, y) @ v
    assert torch.allclose(hessian_product(objective, psi, u, y)(v), dense_h,
                          rtol=1e-9, atol=1e-12)


def test_first_order_maml_gradient_is_the_gradient_at_the_adapted_weights(problem):
    objective, omega, train, test = problem
    tr_u, tr_y, te_u, te_y = train.u[0], train.y[0], test.u[0], test.y[0]
    out = FirstOrderMamlTaskGradient(objective, 7, LR)(omega, tr_u, tr_y, te_u, te_y)
    psi = omega.clone()
    for _ in range(7):     # eq. (inner), written with plain autograd
        p = psi.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(objective.loss(p, tr_u, tr_y), p)
        psi = psi - LR * g
    p = psi.clone().requires_grad_(True)
    (g_test,) = torch.autograd.grad(objective.loss(p, te_u, te_y), p)
    assert torch.allclose(out.adapted, psi, rtol=1e-12, atol=1e-14)
    assert torch.allclose(out.grad, g_test, rtol=1e-10, atol=1e-14)


def test_unrolled_maml_gradient_equals_autograd_through_the_inner_loop(problem):
    objective, omega, train, test = problem
    tr_u, tr_y, te_u, te_y = train.u[1], train.y[1], test.u[1], test.y[1]
    out = UnrolledMamlTaskGradient(objective, 5, LR)(omega, tr_u, tr_y, te_u, te_y)
    w = omega.clone().requires_grad_(True)
    psi = w
    for _ in range(5):
        (g,) = torch.autograd.grad(objective.loss(psi, tr_u, tr_y), psi, create_graph=True)
        psi = psi - LR * g
    (expected,) = torch.autograd.grad(objective.loss(psi, te_u, te_y), w)
    assert torch.allclose(out.grad, expected, rtol=1e-9, atol=1e-13)
    first = FirstOrderMamlTaskGradient(objective, 5, LR)(omega, tr_u, tr_y, te_u, te_y).grad
    assert not torch.allclose(out.grad, first, rtol=1e-3), 'second-order terms must matter'


@pytest.mark.parametrize('method', ['imaml', 'maml', 'maml_unrolled'])
def test_vmap_over_tasks_equals_the_python_loop(problem, method):
    objective, omega, train, test = problem
    args = (omega, train.u, train.y, test.u, test.y)
    config = MetaConfig(method=method, inner_steps=4, cg_steps=4, backend='eager')
    batched = batch_gradient_fn(objective, config)(*args)
    looped = batch_gradient_fn(objective, MetaConfig(method=method, inner_steps=4, cg_steps=4,
                                                     vectorise=False, backend='eager'))(*args)
    for a, b in zip(batched, looped):
        assert a.shape[0] == 3
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12, equal_nan=True)
