"""The report's held-out target set: size, seed stream, dynamics, and l_SSM against numpy."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_model.weights_codec import fields_from_weights, weights_from_fields
from metampc_learner import data, oracle
from metampc_learner.data import (simulate_source, simulate_target, SourceConfig, Trajectory,
                                  Windows)
from metampc_learner.heldout import (HELDOUT_SAMPLES, heldout_loss, heldout_seed,
                                     model_heldout_loss, plant_source, target_heldout)
from metampc_learner.oracle import oracle_data
from metampc_plant.integrate import rk4_sample
from metampc_plant.registry import get_family

torch.set_num_threads(1)
SOURCE = SourceConfig(episode_samples=60).resolved()    # the family's dt, bounds and box
THETA = -0.7


def _numpy_loss(params, norm: Normalisation, config: NssmConfig, trajs) -> float:
    """l_SSM by hand: every window of H + T samples, MLP encoder, latent recursion."""
    p = {k: v.double().numpy() for k, v in params.items()}
    n_h, n_t = config.history, config.loss_horizon
    errors = []
    for traj in trajs:
        u = (traj.u - norm.u_mean) / norm.u_std
        y = (traj.y - norm.y_mean) / norm.y_std
        for s in range(len(traj) - n_h - n_t + 1):
            h = np.concatenate([u[s:s + n_h], y[s:s + n_h]], axis=1).reshape(-1)
            for i in range(len(config.hidden) + 1):
                h = p[f'encoder.{i}.weight'] @ h + p[f'encoder.{i}.bias']
                h = np.maximum(h, 0) if i < len(config.hidden) else h
            z, sq = h, 0.0
            for k in range(s + n_h, s + n_h + n_t):
                z = p['A'] @ z + p['B'] @ u[k]
                sq += np.sum((p['C'] @ z - y[k]) ** 2)
            errors.append(sq / n_t)
    return float(np.mean(errors))


def test_the_set_has_the_samples_of_bounded_theta_star_episodes():
    trajs = target_heldout(THETA, SOURCE, run_seed=3)
    assert sum(len(t) for t in trajs) == HELDOUT_SAMPLES >= 2000
    assert len(trajs) == -(-HELDOUT_SAMPLES // SOURCE.episode_samples)
    for t in trajs:     # every step is the plant core's RK4 sample of theta* under u_{k+1}
        assert np.abs(t.y).max() <= SOURCE.state_bound
        assert np.all((SOURCE.excitation.u_min <= t.u) & (t.u <= SOURCE.excitation.u_max))
        x_next = rk4_sample(get_family('vanderpol'), t.y[:-1], t.u[1:],
                            np.full((len(t) - 1, 1), THETA), SOURCE.dt, SOURCE.substeps)
        np.testing.assert_allclose(x_next, t.y[1:], rtol=0, atol=1e-12)


def test_seeded_and_apart_from_the_runs_own_seeds():
    first, again = target_heldout(THETA, SOURCE, 3), target_heldout(THETA, SOURCE, 3)
    assert all(np.array_equal(a.y, b.y) and np.array_equal(a.u, b.u)
               for a, b in zip(first, again))
    other = target_heldout(THETA, SOURCE, 4)
    assert not np.array_equal(first[0].y, other[0].y)
    # The run's seed s drives the collection, the oracle's episodes (s, s + 1) and the source
    # set; no held-out episode starts where one of those does.
    seeds = {heldout_seed(s) for s in range(100)}
    assert len(seeds) == 100 and not seeds & set(range(102))
    starts = {tuple(t.y[0]) for t in first}
    for s in (3, 4):
        drawn = oracle_data(THETA, SOURCE, 40, s) + simulate_target(THETA, SOURCE, 300, s)
        assert not starts & {tuple(t.y[0]) for t in drawn}


@pytest.mark.parametrize('run_seed', [0, 3, 5])
def test_no_held_out_episode_starts_near_a_training_or_oracle_start(monkeypatch, run_seed):
    """Pins the held-out set's independence from the run's own draws, on the initial states
    x0 themselves (a trajectory holds samples 1..K, so its first sample also depends on the
    input and hides a shared x0). Independent answer: the seeds and x0 arrays actually handed
    to the batch simulator, spied on, for the held-out set and for everything the run seeded
    with s: the oracle's episodes (s and s + 1), a target collection (s) and the source set
    (s). The held-out seed must be none of those, and every held-out x0 must lie more than
    1e-3 (max norm) from every training / oracle x0 (measured: >= 2.9e-3 for these seeds,
    while a set drawn with the run's seed shares its x0 exactly)."""
    seeds, starts = [], []
    real_episodes, real_simulate = data.simulate_episodes, data.simulate

    def spy_episodes(thetas, config, seed):
        seeds.append(int(seed))
        return real_episodes(thetas, config, seed)

    def spy_simulate(thetas, x0, u_seq, config):
        starts.append(np.array(x0, dtype=float))
        return real_simulate(thetas, x0, u_seq, config)

    monkeypatch.setattr(data, 'simulate_episodes', spy_episodes)
    monkeypatch.setattr(oracle, 'simulate_episodes', spy_episodes)
    monkeypatch.setattr(data, 'simulate', spy_simulate)
    target_heldout(THETA, SOURCE, run_seed)
    held_seeds, held_starts = set(seeds), np.concatenate(starts)
    assert held_seeds == {heldout_seed(run_seed)}
    seeds.clear()
    starts.clear()
    oracle_data(THETA, SOURCE, 100, run_seed)
    oracle_data(THETA, SOURCE, 20, run_seed + 1)
    simulate_target(THETA, SOURCE, 300, run_seed)
    simulate_source(replace(SOURCE, n_systems=100, seed=run_seed))
    assert {run_seed, run_seed + 1} <= set(seeds) and not held_seeds & set(seeds)
    drawn = np.concatenate(starts)
    assert len(held_starts) >= HELDOUT_SAMPLES // SOURCE.episode_samples and len(drawn) >= 300
    gap = np.abs(held_starts[:, None, :] - drawn[None, :, :]).max(axis=-1)
    assert gap.min() > 1e-3


def test_plant_source_takes_the_plants_sampling_bounds_and_box():
    source = plant_source(SOURCE, dt=0.05, substeps=4, u_min=[-0.8], u_max=[0.5],
                          state_bound=6.0)
    assert (source.dt, source.substeps, source.state_bound) == (0.05, 4, 6.0)
    assert (source.excitation.u_min, source.excitation.u_max) == ((-0.8,), (0.5,))
    assert source.excitation.kind == SOURCE.excitation.kind
    assert source.episode_samples == SOURCE.episode_samples and SOURCE.dt == 0.1


def test_loss_of_a_published_model_equals_the_numpy_rollout():
    config = NssmConfig(history=3, loss_horizon=4, hidden=(8, 6), n_z=3)
    norm = Normalisation([0.1], [0.6], [0.2, -0.1], [2.5, 3.0])
    params = init_params(config, seed=5)
    params['A'] = params['A'] * 0.9
    trajs = [Trajectory(t.steps[:12], t.u[:12], t.y[:12])
             for t in target_heldout(THETA, SOURCE, 1)[:3]]
    expected = _numpy_loss(params, norm, config, trajs)
    windows = Windows.from_trajectories(trajs, norm, config)
    assert len(windows) == 3 * 6
    assert heldout_loss(Nssm(config, norm), params, windows) == pytest.approx(expected, rel=1e-5)
    # Through the message fields: the decoded model, its own normalisation, the learner's T
    # (the message carries none; the decoded config has the default).
    decoded = weights_from_fields(fields_from_weights(config, norm, params))
    assert decoded.config.loss_horizon != config.loss_horizon
    assert model_heldout_loss(decoded, trajs, config.loss_horizon) == pytest.approx(
        expected, rel=1e-5)
    other = replace(norm, y_std=np.array([1.0, 1.0]))
    assert _numpy_loss(params, other, config, trajs) != pytest.approx(expected, rel=1e-3)
    assert np.isnan(heldout_loss(Nssm(config, norm), params, Windows.from_trajectories(
        trajs, norm, replace(config, loss_horizon=20))))


def _arx2_trajectories(n_traj: int, n: int = 60, seed: int = 0):
    """Trajectories of a stable ARX(2) plant (2 outputs, 1 input) with a little noise."""
    rng = np.random.default_rng(seed)
    a1, a2 = np.array([[0.5, 0.2], [-0.1, 0.6]]), np.array([[0.1, 0.0], [0.05, -0.2]])
    b0, b1 = np.array([1.0, -0.5]), np.array([0.3, 0.2])
    out = []
    for _ in range(n_traj):
        u, y = rng.uniform(-1, 1, (n, 1)), np.zeros((n, 2))
        for t in range(2, n):
            y[t] = (a1 @ y[t - 1] + a2 @ y[t - 2] + b0 * u[t, 0] + b1 * u[t - 1, 0]
                    + 0.01 * rng.normal(size=2))
        out.append(Trajectory(np.arange(n), u, y))
    return out


def test_a_feature_narx_is_scored_on_the_samples_an_nssm_predicts():
    """The same least-squares ARX(2), once as an NSSM of history H (arx.arx_nssm) and once as
    a feature NARX whose feature columns are zero (narx_learning.arx_model): with `history` H
    both are scored on the same T predicted samples of each window, so on the same loss;
    from the start (history 0) the NARX's windows are others."""
    from metampc_learner.arx import arx_nssm
    from metampc_learner.narx_learning import arx_model
    from metampc_model.feature_narx import FeatureNarx, init_params as narx_init
    from metampc_model.narx_shape import NarxShape
    from metampc_model.weights_codec import fields_from_narx, model_from_fields
    trajs = _arx2_trajectories(10)
    norm = Normalisation([0.0], [0.6], [0.2, -0.1], [1.5, 1.0])
    history, horizon = 6, 4
    base = NssmConfig(history=history, loss_horizon=horizon, hidden=(16, 16), n_z=5)
    config, arx_norm, params = arx_nssm(trajs[:4], 2, base, norm)
    nssm = weights_from_fields(fields_from_weights(config, arx_norm, params))
    shape = NarxShape(n_u=1, n_y=2, order=2, features=4, hidden=(8,))
    narx = arx_model(FeatureNarx(shape, norm, narx_init(shape, 0)),
                     [(t.u, t.y) for t in trajs[:4]])
    decoded = model_from_fields(fields_from_narx(shape, norm, narx.params))
    held = trajs[4:]
    expected = model_heldout_loss(nssm, held, horizon)
    # (the NSSM's weights are float32 on the message)
    assert model_heldout_loss(decoded, held, horizon, history) == pytest.approx(expected,
                                                                                rel=1e-3)
    assert model_heldout_loss(decoded, held, horizon) != pytest.approx(expected, rel=1e-2)
