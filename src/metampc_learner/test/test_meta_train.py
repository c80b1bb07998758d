"""Meta-training loop: determinism, non-finite tasks, progress, Algorithm 1's collector, the
divergence guard."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from metampc_model.nssm import init_params, Nssm, prediction_loss
from metampc_model.nssm_config import NssmConfig
from metampc_learner.data import (normalisation_from, simulate_episodes, simulate_source,
                                  SourceConfig, SourceData, SourceSet, Trajectory)
from metampc_learner import meta_train as meta_module
from metampc_learner.meta_train import (meta_train, MetaConfig, MetaTrainingError,
                                        task_gradient_fn)
from metampc_learner.objective import FlatObjective

torch.set_num_threads(1)
TINY = NssmConfig(history=4, loss_horizon=5, hidden=(16, 16), n_z=3)
SRC = SourceConfig(n_systems=6, episodes_per_system=1, episode_samples=60, seed=3)


def _fast(**kw):
    base = dict(iterations=3, batch_size=4, inner_steps=3, cg_steps=3, windows_per_task=8)
    base.update(kw)
    return MetaConfig(**base)


def _source(data=None, max_collected=20000):
    data = simulate_source(SRC) if data is None else data
    clean = [t for ts in data.trajectories for t in ts if np.abs(t.y).max() < 100]
    norm = normalisation_from(clean)
    return Nssm(TINY, norm), SourceSet(data, norm, TINY, max_collected=max_collected)


@pytest.mark.parametrize('method', ['imaml', 'maml', 'maml_unrolled'])
def test_same_seed_gives_bitwise_the_same_weights(method):
    runs = []
    for seed in (7, 7, 8):
        model, source = _source()
        runs.append(meta_train(model, source, _fast(method=method, seed=seed)))
    a, b, c = runs
    assert all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    assert a.losses == b.losses
    assert not torch.equal(a.params['A'], c.params['A'])
    assert all(np.isfinite(a.losses)) and a.skipped == 0


def test_source_simulation_is_seeded():
    a, b = simulate_source(SRC), simulate_source(SRC)
    assert np.array_equal(a.thetas, b.thetas)
    for ta, tb in zip(a.trajectories, b.trajectories):
        assert all(np.array_equal(x.y, y.y) and np.array_equal(x.u, y.u) for x, y in zip(ta, tb))


def _poisoned(n_bad):
    """Six systems; the first n_bad have outputs so large that the float32 loss overflows."""
    data = simulate_source(SRC)
    for i in range(n_bad):
        t = data.trajectories[i][0]
        data.trajectories[i] = [Trajectory(t.steps, t.u, t.y * 1e30)]
    return data


def test_non_finite_task_is_skipped_and_counted():
    model, source = _source(_poisoned(1))
    reports = []
    # Every task, every step: no task held out for validation.
    result = meta_train(model, source, _fast(batch_size=6, iterations=4, validation_tasks=0),
                        progress=reports.append)
    assert result.skipped == 4
    assert [r.skipped for r in reports] == [1, 2, 3, 4]
    assert all(np.isfinite(result.losses))
    assert all(torch.isfinite(v).all() for v in result.params.values())


def _record_sgd(monkeypatch):
    """Replace Adam by plain SGD that records the gradient of every step; the record."""
    given = []

    class RecordingSgd(torch.optim.SGD):
        def step(self, closure=None):
            given.append(self.param_groups[0]['params'][0].grad.clone())
            return super().step(closure)

    monkeypatch.setattr(torch.optim, 'Adam', RecordingSgd)
    return given


def test_outer_step_gets_the_mean_of_the_finite_task_gradients(monkeypatch):
    """Eq. (outer): the optimiser is handed 1/B' sum of the B' finite tasks' meta-gradients.

    Adam is replaced by a recording SGD (Adam's update is invariant to the gradient's scale, so
    it would hide a wrong average); the steps are redone by hand with a Python loop over tasks.
    """
    given = _record_sgd(monkeypatch)
    model, source = _source(_poisoned(1))
    config = _fast(method='imaml', batch_size=6, iterations=2, lr_outer=0.01,
                   lr_schedule='constant', validation_tasks=0)
    result = meta_train(model, source, config)
    objective = FlatObjective(model)
    task_fn = task_gradient_fn(objective, config)
    rng = np.random.default_rng(config.seed)
    omega = objective.spec.flatten(init_params(TINY, config.seed))
    for step in range(2):
        tasks = rng.choice(len(source), size=6, replace=False)
        train, test = source.sample(tasks, config.windows_per_task, rng)
        outs = [task_fn(omega, train.u[b], train.y[b], test.u[b], test.y[b]) for b in range(6)]
        finite = [o.grad for o in outs if torch.isfinite(o.test_loss) and o.grad.isfinite().all()]
        assert len(finite) == 5
        mean = torch.stack(finite).mean(dim=0)
        assert float((given[step] - mean).norm()) <= 1e-4 * float(mean.norm())
        omega = omega - 0.01 * mean
    got = objective.spec.flatten(result.params)
    assert float((got - omega).norm()) <= 1e-5 * float(omega.norm())


def test_training_stops_naming_the_tasks_when_most_of_a_batch_keeps_failing():
    model, source = _source(_poisoned(4))
    with pytest.raises(MetaTrainingError) as err:
        meta_train(model, source, _fast(batch_size=6, iterations=10, max_bad_steps=2,
                                        validation_tasks=0))
    message = str(err.value)
    assert '2 consecutive steps (up to step 2)' in message
    for i in range(4):
        assert f'system {i}, theta=[{source.thetas[i][0]:.3f}]' in message
    assert 'system 5' not in message


def test_progress_reports_every_outer_step():
    reports = []
    model, source = _source()
    result = meta_train(model, source, _fast(iterations=4), progress=reports.append)
    assert [r.iteration for r in reports] == [1, 2, 3, 4]
    assert all(r.total == 4 and r.skipped == 0 for r in reports)
    assert [r.loss for r in reports] == result.losses
    assert all(np.isfinite(r.cg_residual) and 0 <= r.cg_residual < 1 for r in reports)
    assert np.all(np.diff([r.elapsed for r in reports]) >= 0)
    maml = []
    meta_train(model, source, _fast(iterations=2, method='maml'), progress=maml.append)
    assert all(np.isnan(r.cg_residual) for r in maml)


def test_collector_receives_adapted_weights_and_growth_is_capped():
    calls = []

    def collector(task, theta, params):
        calls.append((task, theta, {k: v.shape for k, v in params.items()}))
        (traj,), _ = simulate_episodes([theta], SourceConfig(episode_samples=30), seed=len(calls))
        return [] if traj is None else [traj]

    model, source = _source(max_collected=100)
    result = meta_train(model, source, _fast(iterations=3), collector=collector)
    assert len(calls) == 3 * 4
    assert all(shapes == {k: v.shape for k, v in model.params().items()}
               for _, _, shapes in calls)
    assert all(theta == source.thetas[task] for task, theta, _ in calls)
    assert result.collected_samples == source.collected_samples <= 100
    assert result.collected_samples + result.dropped_samples == 30 * len(calls)
    assert result.dropped_samples > 0


def test_cosine_schedule_anneals_the_outer_rate_to_zero(monkeypatch):
    """Step k of N uses beta_out (1 + cos(pi k / N)) / 2 (SGDR's formula, written out here):
    with a recording SGD the final weights are omega_0 - sum_k rate_k g_k."""
    given = _record_sgd(monkeypatch)
    model, source = _source()
    n, lr = 4, 0.02
    result = meta_train(model, source, _fast(method='maml', iterations=n, lr_outer=lr,
                                             lr_schedule='cosine'))
    rates = [lr * (1 + np.cos(np.pi * k / n)) / 2 for k in range(n)]
    assert result.lr_outer == pytest.approx(rates, rel=1e-12)
    objective = FlatObjective(model)
    omega = objective.spec.flatten(init_params(TINY, 0))
    for rate, g in zip(rates, given):
        omega = omega - rate * g
    got = objective.spec.flatten(result.params)
    assert float((got - omega).norm()) <= 1e-5 * float(omega.norm())
    constant = meta_train(*_source(), _fast(method='maml', iterations=n, lr_outer=lr))
    assert constant.lr_outer == [lr] * n


def test_config_validation():
    for bad in (dict(method='reptile'), dict(curvature='fisher'), dict(gamma=0.0),
                dict(method='maml', gamma=0.0), dict(lr_schedule='cosine ', iterations=1.5),
                dict(lr_schedule='linear'),
                dict(batch_size=0), dict(lr_outer=0.0)):
        with pytest.raises(ValueError):
            MetaConfig(**bad).validate()
    MetaConfig(method='maml').validate()


def test_source_set_without_usable_tasks_is_refused():
    data = SourceData(np.array([0.1]), [[]], escaped=1)
    with pytest.raises(ValueError, match='no source system'):
        SourceSet(data, normalisation_from(simulate_source(SRC).trajectories[0]), TINY)


@pytest.mark.parametrize('method', ['imaml', 'maml'])
def test_anchor_adds_the_weighted_gradient_of_the_loss_before_adaptation(method):
    model, source = _source()
    objective = FlatObjective(model)
    omega = objective.spec.flatten(init_params(TINY, 5))
    train, test = source.sample(np.arange(3), 8, np.random.default_rng(5))
    free = task_gradient_fn(objective, _fast(method=method))
    anchored = task_gradient_fn(objective, _fast(method=method, init_loss_weight=0.3))
    for b in range(3):
        task = (train.u[b], train.y[b], test.u[b], test.y[b])
        w = omega.clone().requires_grad_(True)
        loss = prediction_loss(model, objective.spec.unflatten(w), test.u[b], test.y[b])
        reference, = torch.autograd.grad(loss, w)  # at omega, by autograd
        a, f = anchored(omega, *task), free(omega, *task)
        assert torch.allclose(a.grad, f.grad + 0.3 * reference, rtol=1e-5, atol=1e-7)
        assert torch.equal(a.test_loss, f.test_loss) and torch.equal(a.adapted, f.adapted)


def test_a_forced_loss_spike_is_rolled_back_to_the_best_checkpoint(monkeypatch):
    """At outer step 13 the meta-gradient is multiplied by 1e4 (a forced spike: Adam is
    replaced by SGD, which does not normalise it away). The validation at step 15 sees the
    held-out loss explode, restores the weights and optimiser state of the best validation
    (step 10 at the latest), halves beta_out, and training goes on to a finite end; the
    returned weights are the best checkpoint's, whose validation loss is recomputed here."""
    _record_sgd(monkeypatch)
    model, source = _source(simulate_source(replace(SRC, n_systems=10)))
    real = meta_module.batch_gradient_fn
    calls = {'n': 0}

    def spiking(objective, config):
        fn = real(objective, config)

        def wrapped(omega, *windows):
            out = fn(omega, *windows)
            if windows[0].shape[0] == config.batch_size:    # a training step, not a validation
                calls['n'] += 1
                if calls['n'] == 13:
                    return out._replace(grad=out.grad * 1e4)
            return out
        return wrapped

    monkeypatch.setattr(meta_module, 'batch_gradient_fn', spiking)
    reports = []
    config = _fast(iterations=30, batch_size=4, lr_outer=0.05, validation_tasks=2,
                   validation_every=5, lr_schedule='constant')
    result = meta_train(model, source, config, progress=reports.append)
    losses = dict(result.validation_losses)
    assert sorted(losses) == [0, 5, 10, 15, 20, 25, 30]
    assert result.rollbacks == [15]
    assert losses[15] > 10 * min(losses[s] for s in (0, 5, 10))
    assert result.best_iteration in (0, 5, 10, 20, 25, 30)
    assert losses[result.best_iteration] == min(losses.values())
    assert result.lr_outer[15] == pytest.approx(0.025)          # halved from step 16 on
    assert [r.rollbacks for r in reports][14:16] == [1, 1] and reports[13].rollbacks == 0
    guard = meta_module.DivergenceGuard(source, config, real(FlatObjective(model), config),
                                        torch.device('cpu'))
    again = guard.loss(FlatObjective(model).spec.flatten(result.params))
    assert again == pytest.approx(losses[result.best_iteration], rel=1e-6)
