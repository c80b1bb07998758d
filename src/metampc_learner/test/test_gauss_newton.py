"""Levenberg-Marquardt adaptation steps (gauss_newton.py) against a dense solve, and in use."""
import pytest
import torch

from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.adapt import adapt, AdaptConfig
from metampc_learner.data import normalisation_from, simulate_target, SourceConfig, Windows
from metampc_learner.gauss_newton import lm_step
from metampc_learner.objective import FlatObjective

torch.set_num_threads(1)
SMALL = NssmConfig(history=3, loss_horizon=4, hidden=(6,), n_z=2)
TINY = NssmConfig(history=4, loss_horizon=5, hidden=(16, 16), n_z=3)


def _windows(config, dtype=torch.float32, samples=200):
    source = SourceConfig(episode_samples=100)
    train = simulate_target(0.6, source, samples, seed=1)
    held = simulate_target(0.6, source, 100, seed=2)
    norm = normalisation_from(train)
    return (Nssm(config, norm, dtype=dtype),
            Windows.from_trajectories(train, norm, config, dtype),
            Windows.from_trajectories(held, norm, config, dtype))


@pytest.mark.parametrize('gamma, mu', [(0.0, 1e-3), (0.5, 1e-2)])
def test_one_step_is_the_damped_gauss_newton_step_of_a_dense_jacobian(gamma, mu):
    """With as many CG iterations as weights (float64) the step solves
    (2/(NT) J'J + (gamma + mu) I) d = -(-2/(NT) J'(y - y_hat) + gamma (psi - anchor)),
    J and the residuals formed densely here (torch.func.jacrev), not by the code's products."""
    model, train, _ = _windows(SMALL, torch.float64, samples=60)
    objective = FlatObjective(model)
    anchor = objective.spec.flatten(init_params(SMALL, 1, torch.float64))
    psi = anchor + 0.05 * torch.randn(anchor.shape, dtype=torch.float64,
                                      generator=torch.Generator().manual_seed(2))
    new, rate, _ = lm_step(objective, psi, anchor, train.u, train.y, gamma, mu, psi.numel())
    assert rate == pytest.approx(1.0 / (gamma + mu))      # the first trial is taken here

    def predict(p):
        return objective.predict(p, train.u, train.y).reshape(-1)
    jac = torch.func.jacrev(predict)(psi)                  # (N T n_y, P)
    residual = train.y[:, SMALL.history:].reshape(-1) - predict(psi)
    scale = 2.0 / (train.u.shape[0] * SMALL.loss_horizon)
    gradient = -scale * jac.T @ residual + gamma * (psi - anchor)
    system = scale * jac.T @ jac + (gamma + mu) * torch.eye(psi.numel(), dtype=torch.float64)
    expected = psi + torch.linalg.solve(system, -gradient)
    torch.testing.assert_close(new, expected, rtol=1e-6, atol=1e-8)


def test_a_step_that_does_not_decrease_is_damped_until_one_does():
    """From mu = 1e-12 the undamped step overshoots on this non-linear loss (seen here); the
    returned step decreases the proximal objective at a larger damping."""
    model, train, _ = _windows(SMALL, torch.float64, samples=60)
    objective = FlatObjective(model)
    psi = objective.spec.flatten(init_params(SMALL, 3, torch.float64))
    before = float(objective.prox_objective(psi, psi, train.u, train.y, 0.0))
    new, rate, mu = lm_step(objective, psi, psi, train.u, train.y, 0.0, 1e-12, 20)
    assert 0.0 < rate < 1e11                                 # 1 / mu: not the first trial's
    assert float(objective.prox_objective(new, psi, train.u, train.y, 0.0)) < before


def test_adaptation_by_gauss_newton_decreases_and_beats_gradient_steps():
    """Every step decreases the training loss (gamma = 0: the objective), and 5 steps reach a
    lower training and held-out loss than 50 backtracked gradient steps at the tuned rate of
    van der Pol (config/default.yaml: 0.1)."""
    model, train, held = _windows(TINY)
    init = init_params(TINY, 3)
    lm = adapt(model, init, train, held, AdaptConfig(steps=5, rule='gauss_newton'))
    assert all(b < a for a, b in zip(lm.train_loss, lm.train_loss[1:])), lm.train_loss
    assert len(lm.rates) == 5 and all(r > 0 for r in lm.rates)
    plain = adapt(model, init, train, held, AdaptConfig(steps=50, lr=0.1))
    assert lm.train_loss[-1] < plain.train_loss[-1], (lm.train_loss, plain.train_loss)
    assert lm.heldout_loss[-1] < plain.heldout_loss[-1]
    pulled = adapt(model, init, train, held,
                   AdaptConfig(steps=5, gamma=10.0, rule='gauss_newton'))
    objective = FlatObjective(model)
    start = objective.spec.flatten(init)
    assert float((objective.spec.flatten(pulled.params) - start).norm()) < \
        float((objective.spec.flatten(lm.params) - start).norm())


def test_an_unknown_rule_is_refused_by_name():
    with pytest.raises(ValueError, match='rule'):
        AdaptConfig(rule='newton').validate()
    with pytest.raises(ValueError, match='cg_steps'):
        AdaptConfig(cg_steps=0).validate()
