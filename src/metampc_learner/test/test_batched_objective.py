"""The fast backend (batched_objective.py) against the eager reference (vmap of imaml.py /
maml.py), its device check and its determinism."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from metampc_common.params import ParameterError
from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.batched_objective import BatchedNssm, BatchedTaskGradient
from metampc_learner.curvature import gauss_newton_product
from metampc_learner.data import normalisation_from, simulate_source, SourceConfig, SourceSet
from metampc_learner.meta_train import batch_gradient_fn, meta_train, MetaConfig
from metampc_learner.objective import FlatObjective
from metampc_learner.task_gradient import TaskGradient

torch.set_num_threads(1)
TINY = NssmConfig(history=4, loss_horizon=5, hidden=(16, 16), n_z=3)
SRC = SourceConfig(n_systems=6, episodes_per_system=1, episode_samples=60, seed=3)
CUDA = torch.cuda.is_available()


def _problem(nssm=TINY, dtype=torch.float32, n_tasks=5, windows=8):
    data = simulate_source(SRC)
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    model = Nssm(nssm, norm, dtype=dtype)
    source = SourceSet(data, norm, nssm, dtype=dtype)
    train, test = source.sample(np.arange(n_tasks), windows, np.random.default_rng(4))
    objective = FlatObjective(model)
    omega = objective.spec.flatten(init_params(nssm, 2, dtype))
    return model, source, objective, (omega, train.u, train.y, test.u, test.y)


def _config(**kw):
    base = dict(inner_steps=4, cg_steps=4, batch_size=4, windows_per_task=8, iterations=3)
    base.update(kw)
    return MetaConfig(**base)


def _both(objective, args, **kw):
    """(eager, fast) TaskGradients of the same batch."""
    eager = batch_gradient_fn(objective, _config(backend='eager', **kw))(*args)
    fast_fn = batch_gradient_fn(objective, _config(backend='fast', **kw))
    assert isinstance(fast_fn, BatchedTaskGradient)
    return eager, fast_fn(*args)


def _assert_close(eager: TaskGradient, fast: TaskGradient, rtol, atol):
    for name, a, b in zip(TaskGradient._fields, eager, fast):
        assert a.shape == b.shape, name
        scale = float(a[torch.isfinite(a)].abs().max()) if torch.isfinite(a).any() else 1.0
        assert torch.allclose(a, b, rtol=rtol, atol=atol * scale, equal_nan=True), (
            name, float((a - b).abs().max()), scale)


@pytest.mark.parametrize('method', ['imaml', 'maml'])
@pytest.mark.parametrize('weight', [0.0, 0.3])
def test_fast_meta_gradient_equals_the_eager_reference_in_float32(method, weight):
    """iMAML-GN (CG residual included) and first-order MAML, with and without the anchor:
    the same meta-gradient, test loss, residual and adapted weights to float32 rounding."""
    _, _, objective, args = _problem()
    eager, fast = _both(objective, args, method=method, init_loss_weight=weight)
    assert torch.isfinite(eager.grad).all() and float(eager.grad.abs().max()) > 1e-3
    _assert_close(eager, fast, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize('method', ['imaml', 'maml'])
@pytest.mark.parametrize('stable', [True, False])
def test_fast_meta_gradient_equals_the_eager_reference_in_float64(method, stable):
    """In float64 they agree to ~1e-10: the same mathematics, not an approximation (the head's
    hand-written derivatives through bounded_transition included; one hidden layer)."""
    nssm = NssmConfig(history=3, loss_horizon=4, hidden=(16,), n_z=3, stable_latent=stable)
    _, _, objective, args = _problem(nssm, torch.float64)
    eager, fast = _both(objective, args, method=method, init_loss_weight=0.2)
    _assert_close(eager, fast, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize('hidden', [(), (8, 6, 5)])
def test_several_inputs_and_outputs_and_any_depth_agree_with_the_reference(hidden):
    """n_u = 2, n_y = 4 (quadruple_tank's sizes), no or three hidden layers, random windows."""
    nssm = NssmConfig(n_u=2, n_y=4, history=3, loss_horizon=4, hidden=hidden, n_z=3)
    gen = torch.Generator().manual_seed(1)
    u, y = (torch.randn(3, 6, 7, n, generator=gen, dtype=torch.float64) for n in (2, 4))
    model = Nssm(nssm, dtype=torch.float64)
    objective = FlatObjective(model)
    omega = objective.spec.flatten(init_params(nssm, 3, torch.float64))
    args = (omega, u, 0.5 * y, u.flip(1), y.flip(1))
    for method in ('imaml', 'maml'):
        eager, fast = _both(objective, args, method=method, init_loss_weight=0.1)
        _assert_close(eager, fast, rtol=1e-9, atol=1e-10)


def test_refused_inner_steps_agree_with_the_reference():
    """Rates too large: the safeguard refuses steps and halves per task, the same way."""
    _, _, objective, args = _problem()
    omega, tr_u, tr_y = args[:3]
    for lr in (2.0, 5.0):
        refused = []
        for b in range(tr_u.shape[0]):          # the reference's rates after 8 steps
            psi, rate = omega, torch.tensor(lr)
            for _ in range(8):
                psi, rate = objective.prox_step(psi, omega, tr_u[b], tr_y[b], rate, 1.0)
            refused.append(float(rate) < lr)
        assert any(refused)
        eager, fast = _both(objective, args, method='imaml', lr_inner=lr, inner_steps=8)
        _assert_close(eager, fast, rtol=1e-4, atol=1e-5)


def test_gauss_newton_product_equals_the_reference():
    model, _, objective, (omega, tr_u, tr_y, _, _) = _problem(dtype=torch.float64)
    net = BatchedNssm(model)
    psi = omega + 0.01 * torch.randn(tr_u.shape[0], omega.numel(), dtype=torch.float64,
                                     generator=torch.Generator().manual_seed(0))
    v = torch.randn_like(psi)
    got = net.gauss_newton(psi, net.windows(tr_u, tr_y))(v, torch.empty_like(v))
    for b in range(psi.shape[0]):
        ref = gauss_newton_product(objective, psi[b], tr_u[b], tr_y[b])(v[b])
        assert torch.allclose(got[b], ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize('method', ['imaml', 'maml'])
def test_meta_training_fast_and_eager_end_close(method):
    """Three outer steps of Algorithm 1 with either backend: the same weights to float32
    rounding (Adam amplifies rounding a little; still <= 1e-4 relative)."""
    model, source, objective, _ = _problem()
    runs = [meta_train(model, source, _config(method=method, backend=b, init_loss_weight=0.1))
            for b in ('eager', 'fast')]
    a, b = (objective.spec.flatten(r.params) for r in runs)
    assert float((a - b).norm()) <= 1e-4 * float(a.norm())
    assert np.allclose(runs[0].losses, runs[1].losses, rtol=1e-4)


@pytest.mark.parametrize('method', ['imaml', 'maml'])
def test_fast_backend_gives_bitwise_the_same_weights_for_the_same_seed(method):
    model, source, _, _ = _problem()
    config = _config(method=method, init_loss_weight=0.1, seed=5)
    a, b = (meta_train(model, source, config) for _ in range(2))
    assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    assert a.losses == b.losses
    assert np.array_equal(a.cg_residuals, b.cg_residuals, equal_nan=True)


def test_fast_backend_covers_imaml_gauss_newton_and_first_order_maml_only():
    assert MetaConfig().fast and MetaConfig(method='maml').fast
    assert not MetaConfig(curvature='hessian').fast
    assert not MetaConfig(method='maml_unrolled').fast
    assert not MetaConfig(backend='eager').fast
    for bad in (dict(backend='jit'), dict(device='gpu')):
        with pytest.raises(ValueError):
            MetaConfig(**bad).validate()


@pytest.mark.skipif(CUDA, reason='this machine has CUDA')
def test_cuda_is_refused_at_validation_when_absent():
    """A clear ParameterError from validate(), so the learner node exits with status 2 (the
    parameter) or refuses the request."""
    with pytest.raises(ParameterError, match='device must be cpu here: cuda was asked'):
        MetaConfig(device='cuda').validate()
    from metampc_learner.learner_params import parse_params, PARAMETERS  # (osqp: not on GPU)
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    assert (values['backend'], values['device']) == ('fast', 'cpu')
    with pytest.raises(ParameterError, match='device must be cpu here'):
        parse_params({**values, 'device': 'cuda'})
    assert parse_params({**values, 'backend': 'eager'}).meta.backend == 'eager'


@pytest.mark.skipif(not CUDA, reason='no CUDA device')
@pytest.mark.parametrize('method', ['imaml', 'maml'])
def test_fast_backend_on_cuda_equals_the_cpu(method):
    _, _, objective, args = _problem()
    cpu = batch_gradient_fn(objective, _config(method=method))(*args)
    gpu = batch_gradient_fn(objective, replace(_config(method=method), device='cuda'))(
        *(x.cuda() for x in args))
    assert gpu.grad.is_cuda
    _assert_close(cpu, TaskGradient(*(x.cpu() for x in gpu)), rtol=1e-4, atol=1e-5)
