"""The latent consistency term of the training loss (nssm.training_loss, docs/learning.md)."""
import torch
from torch.autograd.functional import jacobian
from torch.func import functional_call

from metampc_model.nssm import consistency_loss, Nssm, prediction_loss, training_loss
from metampc_model.nssm_config import NssmConfig
from metampc_learner.batched_objective import BatchedTaskGradient
from metampc_learner.curvature import gauss_newton_product
from metampc_learner.meta_train import batch_gradient_fn, MetaConfig
from metampc_learner.objective import FlatObjective

torch.set_num_threads(1)
SMALL = dict(n_z=3, history=4, hidden=(8,), loss_horizon=5)


def _windows(config, n, seed, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    return (torch.randn(n, config.window, config.n_u, generator=gen, dtype=dtype),
            torch.randn(n, config.window, config.n_y, generator=gen, dtype=dtype))


def _by_recursion(model, p, u, y):
    """l_cons written out step by step: the encoder's state at t+1 and the model's own step
    from its state at t, both run forward under the same inputs; outputs compared."""
    n_h, n_t = model.config.history, model.config.loss_horizon
    with torch.no_grad():
        z_t, z_enc = (model.encode(u[:, j:j + n_h], y[:, j:j + n_h]) for j in (0, 1))
    z_own = z_t @ p['A'].T + u[:, n_h] @ p['B'].T
    total = 0.0
    for k in range(n_t):                 # outputs y_{t+1+k}, inputs u_{t+2..} alike
        total = total + ((z_enc - z_own) @ p['C'].T).square().sum(-1)
        z_enc = z_enc @ p['A'].T
        z_own = z_own @ p['A'].T
    return (total / n_t).mean()


def test_consistency_is_the_disagreement_of_the_two_predictions():
    config = NssmConfig(**SMALL)
    model = Nssm(config, seed=1, dtype=torch.float64)
    p = model.params()
    u, y = _windows(config, 6, 0)
    expected = _by_recursion(model, p, u, y)
    assert float(expected) > 1e-3
    assert torch.allclose(consistency_loss(model, p, u, y), expected, rtol=1e-12)


def test_consistency_is_invariant_to_the_latent_coordinates():
    """z -> M z (last encoder layer, A, B, C transformed): the outputs and l_cons stay, the raw
    latent residual ||rho|| does not (a raw-norm penalty could be gamed by shrinking z)."""
    config = NssmConfig(**SMALL)
    model = Nssm(config, seed=2, dtype=torch.float64)
    p = model.params()
    u, y = _windows(config, 6, 1)
    m = 0.1 * torch.eye(config.n_z, dtype=torch.float64) + 0.05 * torch.randn(
        config.n_z, config.n_z, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    m_inv = torch.linalg.inv(m)
    q = dict(p)
    last = len(config.hidden)
    q[f'encoder.{last}.weight'] = m @ p[f'encoder.{last}.weight']
    q[f'encoder.{last}.bias'] = m @ p[f'encoder.{last}.bias']
    q['A'], q['B'], q['C'] = m @ p['A'] @ m_inv, m @ p['B'], p['C'] @ m_inv
    assert torch.allclose(prediction_loss(model, q, u, y), prediction_loss(model, p, u, y))
    assert torch.allclose(consistency_loss(model, q, u, y), consistency_loss(model, p, u, y),
                          rtol=1e-9)

    def rho(params):
        other = Nssm(config, dtype=torch.float64)
        with torch.no_grad():
            for name, value in params.items():
                other.get_parameter(name).copy_(value)
            n_h = config.history
            z_t = other.encode(u[:, :n_h], y[:, :n_h])
            z_1 = other.encode(u[:, 1:n_h + 1], y[:, 1:n_h + 1])
            return float((z_1 - z_t @ params['A'].T - u[:, n_h] @ params['B'].T).norm())

    assert rho(q) < 0.5 * rho(p)


def test_weight_zero_is_the_paper_loss_and_the_fast_backend():
    config = NssmConfig(**SMALL)
    model = Nssm(config, seed=4)
    objective = FlatObjective(model)
    u, y = _windows(config, 5, 2, torch.float32)
    flat = objective.spec.flatten(model.params())
    p = objective.spec.unflatten(flat)
    assert torch.equal(objective.loss(flat, u, y), prediction_loss(model, p, u, y))
    assert torch.equal(objective.predict(flat, u, y), functional_call(model, p, (u, y)))
    meta = MetaConfig(method='imaml')
    assert isinstance(batch_gradient_fn(objective, meta), BatchedTaskGradient)
    weighted = FlatObjective(Nssm(NssmConfig(**SMALL, consistency_weight=0.5), seed=4))
    assert not isinstance(batch_gradient_fn(weighted, meta), BatchedTaskGradient)
    expected = prediction_loss(model, p, u, y) + 0.5 * consistency_loss(model, p, u, y)
    assert torch.allclose(weighted.loss(flat, u, y), expected)
    assert torch.equal(weighted.loss(flat, u, y), training_loss(weighted.model, p, u, y))


def test_gauss_newton_covers_both_terms():
    """G v = (2 / (N T)) (J_y' J_y + w J_c' J_c) v, the Jacobians taken separately."""
    w = 0.7
    model = Nssm(NssmConfig(**SMALL, consistency_weight=w), seed=5, dtype=torch.float64)
    objective = FlatObjective(model)
    u, y = _windows(model.config, 4, 3)
    psi = objective.spec.flatten(model.params())

    def outputs(flat, consistency):
        return functional_call(model, objective.spec.unflatten(flat), (u, y),
                               {'consistency': consistency}).reshape(-1)

    j_y = jacobian(lambda f: outputs(f, False), psi)
    j_c = jacobian(lambda f: outputs(f, True), psi)
    v = torch.randn(psi.numel(), generator=torch.Generator().manual_seed(6),
                    dtype=torch.float64)
    expected = 2.0 / objective.n_terms(u) * (j_y.T @ (j_y @ v) + w * j_c.T @ (j_c @ v))
    assert torch.allclose(gauss_newton_product(objective, psi, u, y)(v), expected, rtol=1e-9)


def test_training_with_the_term_makes_the_latent_consistent():
    """Gradient descent from the same start: with the term, l_cons ends far lower, while
    l_SSM stays near what l_SSM alone reaches."""
    u, y = _windows(NssmConfig(**SMALL), 64, 7)
    y = torch.cumsum(0.3 * y, dim=1) / 3         # smoother outputs: something to learn
    ends = {}
    for w in (0.0, 1.0):
        model = Nssm(NssmConfig(**SMALL, consistency_weight=w), seed=8, dtype=torch.float64)
        objective = FlatObjective(model)
        psi = objective.spec.flatten(model.params())
        for _ in range(300):
            psi, _ = objective.armijo_step(psi, psi, u, y, 0.5, 0.0)
        p = objective.spec.unflatten(psi)
        ends[w] = (float(prediction_loss(model, p, u, y)), float(consistency_loss(model, p, u, y)))
    assert ends[1.0][1] < 0.2 * ends[0.0][1]
    assert ends[1.0][0] < 1.5 * ends[0.0][0]
