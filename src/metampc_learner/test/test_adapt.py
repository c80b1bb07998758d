"""Meta-inference (eq. infer) and the supervised baseline."""
import numpy as np
import pytest
import torch

from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.adapt import adapt, AdaptConfig, supervised
from metampc_learner.data import normalisation_from, simulate_target, SourceConfig, Windows
from metampc_learner.objective import ARMIJO_C, FlatObjective

torch.set_num_threads(1)
TINY = NssmConfig(history=4, loss_horizon=5, hidden=(16, 16), n_z=3)


@pytest.fixture(scope='module')
def target():
    config = SourceConfig(episode_samples=100)
    train = simulate_target(0.6, config, 200, seed=1)
    held = simulate_target(0.6, config, 100, seed=2)
    norm = normalisation_from(train)
    model = Nssm(TINY, norm)
    return (model, Windows.from_trajectories(train, norm, TINY),
            Windows.from_trajectories(held, norm, TINY))


def _distance(a, b):
    return float(sum((a[k] - b[k]).square().sum() for k in a).sqrt())


def test_adaptation_curves_and_proximal_pull(target):
    model, train, held = target
    init = init_params(TINY, 3)
    plain = adapt(model, init, train, held, AdaptConfig(steps=6, lr=0.05, gamma=0.0))
    assert len(plain.train_loss) == len(plain.heldout_loss) == 7
    objective = FlatObjective(model)
    flat = objective.spec.flatten(init)
    assert plain.heldout_loss[0] == pytest.approx(float(objective.loss(flat, held.u, held.y)))
    assert plain.train_loss[-1] < plain.train_loss[0]
    reports = []
    again = adapt(model, init, train, held, AdaptConfig(steps=6, lr=0.05), reports.append)
    assert again.heldout_loss == plain.heldout_loss
    assert [(r.iteration, r.total) for r in reports] == [(k, 6) for k in range(1, 7)]
    assert [r.loss for r in reports] == plain.heldout_loss[1:]
    prox = adapt(model, init, train, held, AdaptConfig(steps=6, lr=0.05, gamma=10.0))
    assert _distance(prox.params, init) < _distance(plain.params, init)
    none = adapt(model, init, train, held, AdaptConfig(steps=0))
    # Unchanged up to the round trip of A through its stable parameterisation (float32: seen
    # 1.5e-8 on one CPU, 0 on another), far below one step's change.
    assert all(torch.allclose(none.params[k], init[k], rtol=1e-6, atol=1e-7) for k in init)
    assert _distance(none.params, init) < 1e-4 * _distance(plain.params, init)


def test_supervised_starts_from_the_seeded_random_init(target):
    model, train, held = target
    a = supervised(model, train, held, AdaptConfig(steps=2, gamma=5.0), seed=4)
    b = adapt(model, init_params(TINY, 4), train, held, AdaptConfig(steps=2, gamma=0.0))
    assert a.heldout_loss == b.heldout_loss
    assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)


def test_a_step_size_too_large_for_the_curvature_is_caught(target):
    model, train, held = target
    init = init_params(TINY, 3)
    objective = FlatObjective(model)
    flat = objective.spec.flatten(init)
    plain = flat
    for _ in range(5):      # plain gradient descent at this step size diverges
        plain = plain - 5.0 * torch.func.grad(objective.loss)(plain, train.u, train.y)
    diverged = objective.loss(plain, train.u, train.y)
    assert not torch.isfinite(diverged) or diverged > 1e3 * objective.loss(flat, train.u, train.y)
    result = adapt(model, init, train, held, AdaptConfig(steps=15, lr=5.0))
    assert np.all(np.isfinite(result.train_loss))
    assert np.all(np.diff(result.train_loss) <= 1e-3 * np.abs(result.train_loss[:-1]))
    assert result.train_loss[-1] < result.train_loss[0]


def test_adapt_refuses_empty_data(target):
    model, _, held = target
    empty = Windows(held.u[:0], held.y[:0])
    with pytest.raises(ValueError, match='no target windows'):
        adapt(model, init_params(TINY, 0), empty, held, AdaptConfig())
    with pytest.raises(ValueError):
        AdaptConfig(steps=-1).validate()


def test_the_first_step_already_moves_the_loss_at_a_rate_too_large(target):
    """Armijo backtracking from the nominal rate at every step: no step is lost."""
    model, train, held = target
    init = init_params(TINY, 3)
    result = adapt(model, init, train, held, AdaptConfig(steps=3, lr=50.0))
    assert result.train_loss[1] < result.train_loss[0]
    assert all(0 < r < 50.0 for r in result.rates)
    assert np.all(np.diff(result.train_loss) < 0)


def test_a_rate_that_decreases_enough_is_plain_gradient_descent(target):
    model, train, held = target
    init = init_params(TINY, 3, torch.float64)
    model64 = Nssm(TINY, model.norm, dtype=torch.float64)
    train64 = Windows(train.u.double(), train.y.double())
    result = adapt(model64, init, train64, held.__class__(held.u.double(), held.y.double()),
                   AdaptConfig(steps=4, lr=0.01))
    assert result.rates == [0.01] * 4
    objective = FlatObjective(model64)
    flat = objective.spec.flatten(init)
    for _ in range(4):
        flat = flat - 0.01 * torch.func.grad(objective.loss)(flat, train64.u, train64.y)
    got = objective.spec.flatten(result.params)
    torch.testing.assert_close(got, flat, rtol=1e-9, atol=1e-11)


def test_armijo_backtracks_from_a_full_step_that_decreases_too_little(target):
    """Pins the sufficient decrease of ``FlatObjective.armijo_step`` against the rule written
    out here (float64): f(psi - r g) <= f(psi) - ARMIJO_C r ||g||^2, f the proximal objective,
    g its gradient by autograd. The rate lr is found by bisection along -g just short of where
    f climbs back to f(psi) (past the minimum along the line): the full step decreases f, but
    by less than ARMIJO_C lr ||g||^2. So the rule must reject it and halve: the rate taken is
    lr / 2^j with j >= 1, satisfies the rule, and twice it does not."""
    model, train, _ = target
    model64 = Nssm(TINY, model.norm, dtype=torch.float64)
    u, y = train.u.double(), train.y.double()
    objective = FlatObjective(model64)
    psi = objective.spec.flatten(init_params(TINY, 3, torch.float64))
    anchor, gamma = psi + 0.01, 0.5

    def f(x):
        return float(objective.prox_objective(x, anchor, u, y, gamma))

    g = torch.func.grad(objective.prox_objective)(psi, anchor, u, y, gamma)
    f0, g2 = f(psi), float(g.square().sum())

    def phi(r):     # f along the step, less the midpoint of the too-little band
        return f(psi - r * g) - (f0 - 0.5 * ARMIJO_C * r * g2)

    below = 1e-6
    above = below
    while phi(above) < 0:
        below, above = above, 2 * above
    for _ in range(200):
        mid = 0.5 * (below + above)
        below, above = (mid, above) if phi(mid) < 0 else (below, mid)
    lr = below
    full = f(psi - lr * g)
    assert f0 - ARMIJO_C * lr * g2 < full < f0     # decreases, but not sufficiently
    new, rate = objective.armijo_step(psi, anchor, u, y, lr, gamma)
    assert 0 < rate < lr
    halvings = np.log2(lr / rate)
    assert halvings == pytest.approx(round(halvings), abs=1e-9) and round(halvings) >= 1
    torch.testing.assert_close(new, psi - rate * g, rtol=1e-12, atol=1e-14)
    assert f(new) <= f0 - ARMIJO_C * rate * g2
    assert f(psi - 2 * rate * g) > f0 - ARMIJO_C * 2 * rate * g2
