"""Algorithm 1's closed-loop collector (eq. ub) on a tiny NSSM."""
from dataclasses import replace

import numpy as np
import torch

from metampc_controller.mpc import LatentMpc, MpcConfig
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_model.predictor import NssmPredictor
from metampc_learner.data import SourceConfig
from metampc_learner.online_collection import OnlineCollectionConfig, OnlineCollector
from metampc_plant.integrate import rk4_components
from metampc_plant.registry import get_family

TINY = NssmConfig(history=3, loss_horizon=3, hidden=(16,), n_z=3)
NORM = Normalisation([0.0], [0.6], [0.0, 0.0], [3.0, 3.0])
SOURCE = SourceConfig(dt=0.1, substeps=10, state_bound=10.0)
VDP = get_family('vanderpol')
CONFIG = OnlineCollectionConfig(episodes=2, episode_samples=30, horizon=5, noise_std=0.3,
                                seed=4)
# OSQP's wall-clock cap (MpcConfig.time_limit, 50 ms) trips when a loaded machine stalls the
# process and turns a solve into a fallback, so equal runs would differ: out of reach here.
NO_TIME_LIMIT = 30.0


def _collect(theta=0.5, config=CONFIG, source=SOURCE, params=None, task=0):
    collector = OnlineCollector(Nssm(TINY, NORM), config, source)
    # The collector has no setting for the cap: its MPC settings are replaced.
    collector._mpc_config = replace(collector._mpc_config, time_limit=NO_TIME_LIMIT)
    trajs = collector(task, theta, init_params(TINY, 1) if params is None else params)
    return collector, trajs


def test_bounded_finite_trajectories_that_follow_the_plant():
    theta = 0.5
    collector, trajs = _collect(theta)
    assert len(trajs) == 2
    for traj in trajs:
        assert len(traj) == TINY.history + CONFIG.episode_samples
        assert traj.steps.tolist() == list(range(1, len(traj) + 1))
        assert np.all(np.isfinite(traj.y)) and np.abs(traj.y).max() <= SOURCE.state_bound
        assert np.all(np.abs(traj.u) <= 1.0)
        # Index convention: u_{k+1} held over one sample takes y_k (= x_k, no noise) to y_{k+1}.
        for k in range(len(traj) - 1):
            x = rk4_components(VDP, tuple(traj.y[k]), (traj.u[k + 1, 0],), (theta,), SOURCE.dt,
                               SOURCE.substeps)
            assert np.array_equal(x, traj.y[k + 1])
    stats = collector.stats
    assert (stats.calls, stats.episodes, stats.samples) == (1, 2, sum(len(t) for t in trajs))
    assert stats.escaped == stats.model_failures == 0


def test_seeded_reproducible():
    _, a = _collect()
    _, b = _collect()
    _, c = _collect(config=replace(CONFIG, seed=5))
    _, d = _collect(task=1)
    for x, y in zip(a, b):
        assert np.array_equal(x.u, y.u) and np.array_equal(x.y, y.y)
    assert not np.array_equal(a[0].u, c[0].u) and not np.array_equal(a[0].u, d[0].u)


def test_without_noise_the_inputs_are_the_mpc_plan():
    # Eq. (ub) with Sigma = 0: after the H warm-up samples every input is the first input of
    # the latent MPC, replayed here on the returned data (reference 0: ref_bound = 0).
    config = replace(CONFIG, noise_std=0.0, ref_bound=0.0, episodes=1)
    params = init_params(TINY, 1)
    _, (traj,) = _collect(config=config, params=params)
    predictor = NssmPredictor(TINY, NORM, params)
    mpc = LatentMpc(MpcConfig(horizon=5, q=(1.0, 0.0), r=config.r, time_limit=NO_TIME_LIMIT))
    mpc.set_model(predictor.latent)
    n_h = TINY.history
    for t in range(n_h - 1, len(traj) - 1):          # row i holds sample i + 1
        z = predictor.encode(traj.u[t - n_h + 1:t + 1], traj.y[t - n_h + 1:t + 1])
        plan = mpc.solve(z, traj.u[t], np.zeros((5, 2)), traj.y[t], t)
        assert traj.u[t + 1, 0] == min(max(plan.u[0], -1.0), 1.0)


def test_an_escape_ends_the_episode_before_the_box_is_left():
    # The theta = 1 limit cycle reaches |x2| ~ 2.7: a box of 1.5 is left in every episode.
    source = replace(SOURCE, state_bound=1.5)
    collector, trajs = _collect(theta=1.0, source=source)
    assert collector.stats.escaped == 2 and collector.stats.episodes == 2
    assert all(np.abs(t.y).max() <= 1.5 for t in trajs)
    assert all(len(t) < TINY.history + CONFIG.episode_samples for t in trajs)


def test_an_unusable_model_gives_no_data():
    params = init_params(TINY, 1)
    params['A'] = torch.full_like(params['A'], float('nan'))
    collector, trajs = _collect(params=params)
    assert trajs == [] and collector.stats.model_failures == 1 and collector.stats.episodes == 0
