"""HeadRls against the learner's batch ridge, a parameter step, a constant noisy plant, and
bad samples."""
import numpy as np
import pytest
import torch

from metampc_learner.closed_form import ridge
from metampc_model.head_rls import HeadRls

N_Y, N_PHI = 2, 7


def _plant(rng, head, samples, noise):
    """(phi (K, n_phi), y (K, n_y)) of y = head phi + N(0, noise^2), phi with a constant."""
    phi = np.concatenate([rng.normal(size=(samples, N_PHI - 1)), np.ones((samples, 1))], 1)
    return phi, phi @ head.T + noise * rng.normal(size=(samples, N_Y))


def test_without_forgetting_every_estimate_is_the_batch_ridge_of_its_samples():
    rng = np.random.default_rng(0)
    true, prior = rng.normal(size=(N_Y, N_PHI)), rng.normal(size=(N_Y, N_PHI))
    phi, y = _plant(rng, true, 60, 0.3)
    r0 = 0.7
    rls = HeadRls(prior, r0)
    for k in range(len(y)):
        assert rls.take(phi[k], y[k]) == 'taken'
        # closed_form's mean-loss units: r0 = k gamma / 2 over the k samples so far
        batch = ridge(torch.from_numpy(phi[:k + 1]), torch.from_numpy(y[:k + 1]),
                      torch.from_numpy(prior), 2 * r0 / (k + 1)).numpy()
        np.testing.assert_allclose(rls.head, batch, rtol=0, atol=1e-9)
    assert (rls.updates, rls.skipped, rls.resets) == (60, 0, 0)


def test_with_forgetting_it_tracks_a_parameter_step_within_30_samples():
    rng = np.random.default_rng(1)
    before = rng.normal(size=(N_Y, N_PHI))
    after = before + rng.normal(size=(N_Y, N_PHI))
    phi, y = _plant(rng, before, 200, 0.05)
    phi2, y2 = _plant(rng, after, 200, 0.05)
    step = np.linalg.norm(after - before)

    def error_after(forgetting, samples):
        rls = HeadRls(before, 0.1, forgetting)
        for k in range(len(y)):
            rls.take(phi[k], y[k])
        for k in range(samples):
            rls.take(phi2[k], y2[k])
        return np.linalg.norm(rls.head - after) / step

    # lam 0.9 (a memory of 10 samples): within 10 % of the step 30 samples after it (0.06)
    assert error_after(0.9, 30) < 0.1
    # without forgetting the 200 samples before the step hold it back (0.85)
    assert error_after(1.0, 30) > 0.5


def test_the_predictive_std_covers_90_percent_of_one_step_errors_on_a_constant_plant():
    rng = np.random.default_rng(2)
    true = rng.normal(size=(N_Y, N_PHI))
    prior = true + 0.3 * rng.normal(size=(N_Y, N_PHI))
    phi, y = _plant(rng, true, 3000, np.array([0.1, 0.5]))
    for forgetting in (1.0, 0.98):
        rls = HeadRls(prior, 1.0, forgetting)
        inside = []
        for k in range(len(y)):
            std = rls.predictive_std(phi[k])
            if k >= 10:         # a noise estimate of 10 samples first
                inside.append(np.abs(y[k] - rls.head @ phi[k]) <= 1.645 * std)
            rls.take(phi[k], y[k])
        coverage = np.mean(inside, axis=0)
        assert np.all((coverage >= 0.85) & (coverage <= 0.95)), (forgetting, coverage)


def test_regularised_forgetting_keeps_the_precision_and_relaxes_unexcited_directions():
    rng = np.random.default_rng(3)
    prior = rng.normal(size=(N_Y, N_PHI))
    rls = HeadRls(prior, 0.5, 0.9)
    direction = np.zeros(N_PHI)
    direction[0] = 1.0
    rls.take(rng.normal(size=N_PHI), rng.normal(size=N_Y))     # moves every direction
    for _ in range(300):                                       # then only phi_0 is excited
        rls.take(direction, prior @ direction + 1.0)
    eig = np.linalg.eigvalsh(rls.info)
    assert eig.min() >= 0.5 - 1e-9                             # R >= r0 I: no wind-up
    np.testing.assert_allclose(rls.head[:, 1:], prior[:, 1:], atol=1e-9)
    # along phi_0 the stationary mix of the samples (weight 1 / (1 - lam) = 10) and the
    # prior (r0 = 0.5): prior + 10 / 10.5 of the samples' offset 1
    np.testing.assert_allclose(rls.head[:, 0], prior[:, 0] + 10 / 10.5, atol=1e-9)


def test_a_non_finite_sample_leaves_the_estimate_unchanged_and_is_counted():
    rng = np.random.default_rng(4)
    rls = HeadRls(rng.normal(size=(N_Y, N_PHI)), 1.0, 0.95)
    rls.take(rng.normal(size=N_PHI), rng.normal(size=N_Y))
    head, info, noise = rls.head.copy(), rls.info.copy(), rls.noise.copy()
    bad_phi = rng.normal(size=N_PHI)
    bad_phi[3] = np.nan
    assert rls.take(bad_phi, np.zeros(N_Y)) == 'skipped'
    assert rls.take(np.ones(N_PHI), np.array([np.inf, 0.0])) == 'skipped'
    assert np.array_equal(rls.head, head) and np.array_equal(rls.info, info)
    assert np.array_equal(rls.noise, noise)
    assert (rls.updates, rls.skipped, rls.resets) == (1, 2, 0)


def test_an_information_matrix_that_is_not_positive_definite_is_reset_to_the_prior():
    rng = np.random.default_rng(5)
    prior = rng.normal(size=(N_Y, N_PHI))
    rls = HeadRls(prior, 1.0, 0.95)
    for _ in range(5):
        rls.take(rng.normal(size=N_PHI), rng.normal(size=N_Y))
    rls.info = -np.eye(N_PHI)          # as rounding or a broken sample could leave it
    assert rls.take(rng.normal(size=N_PHI), rng.normal(size=N_Y)) == 'reset'
    assert np.array_equal(rls.head, prior) and rls.resets == 1
    assert np.array_equal(rls.info, np.eye(N_PHI)) and np.all(np.isnan(rls.noise))
    assert rls.take(rng.normal(size=N_PHI), rng.normal(size=N_Y)) == 'taken'


def test_bad_settings_are_refused():
    with pytest.raises(ValueError):
        HeadRls(np.zeros((1, 3)), 0.0)
    with pytest.raises(ValueError):
        HeadRls(np.zeros((1, 3)), 1.0, 1.5)
    with pytest.raises(ValueError):
        HeadRls(np.full((1, 3), np.nan), 1.0)
