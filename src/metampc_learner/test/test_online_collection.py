"""Algorithm 1's closed-loop collector (eq. ub) on a tiny NSSM."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from metampc_common.excitation import excitation
from metampc_controller.mpc import LatentMpc, MpcConfig, NO_TIME_LIMIT
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_model.predictor import NssmPredictor
from metampc_learner.data import SourceConfig, Trajectory
from metampc_learner.online_collection import OnlineCollectionConfig, OnlineCollector
from metampc_plant.integrate import rk4_components
from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant

TINY = NssmConfig(history=3, loss_horizon=3, hidden=(16,), n_z=3)
NORM = Normalisation([0.0], [0.6], [0.0, 0.0], [3.0, 3.0])
SOURCE = SourceConfig(dt=0.1, substeps=10, state_bound=10.0)
VDP = get_family('vanderpol')
CONFIG = OnlineCollectionConfig(episodes=2, episode_samples=30, horizon=5, noise_std=0.3,
                                seed=4)


def _collect(theta=0.5, config=CONFIG, source=SOURCE, params=None, task=0):
    collector = OnlineCollector(Nssm(TINY, NORM), config, source)
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


def _reference_old_tick_loop(collector, task, theta, params, call):
    """REFERENCE IMPLEMENTATION, kept only to check the collector against: the collector's own
    tick loop as it was before it ran the controller's tick (commit 71227dd), copied here.
    Returns (trajectories, MPC fallbacks, escapes) of call `call` for source system `task`."""
    cfg, src, fam = collector.config, collector.source, collector.family
    n_h, n_y = collector.model.config.history, collector.model.config.n_y
    predictor = NssmPredictor(collector.model.config, collector.model.norm, params)
    mpc = LatentMpc(collector._mpc_config)
    mpc.set_model(predictor.latent)
    out, fallbacks, escapes = [], 0, 0
    for episode in range(cfg.episodes):
        rng = np.random.default_rng((cfg.seed, task, call, episode))
        mpc.reset()
        n_total = n_h + cfg.episode_samples
        x0 = tuple(rng.uniform(fam.x0_low, fam.x0_high, fam.n_x))
        plant = Plant(replace(src.plant_config(), theta=tuple(np.atleast_1d(theta)), x0=x0))
        warmup = excitation(src.excitation, 1, n_h, src.dt, int(rng.integers(2**31)))[0]
        n_ref = n_total + cfg.horizon
        hold = max(1, int(round(cfg.ref_hold_s / src.dt)))
        tracked = list(fam.tracked)
        centre = np.asarray(fam.reference)[tracked]
        levels = rng.uniform(centre - cfg.ref_bound, centre + cfg.ref_bound,
                             size=(-(-n_ref // hold), len(tracked)))
        ref = np.tile(np.asarray(fam.reference, dtype=float), (n_ref, 1))
        ref[:, tracked] = np.repeat(levels, hold, axis=0)[:n_ref]
        u = np.zeros((n_total + 1, fam.n_u))
        y = np.zeros((n_total + 1, n_y))
        y[0] = plant.output()
        n = 0
        for k in range(1, n_total + 1):
            if k <= n_h:
                u_k = warmup[k - 1]
            else:
                t = k - 1
                z = predictor.encode(u[t - n_h + 1:t + 1], y[t - n_h + 1:t + 1])
                result = mpc.solve(z, u[t], ref[t + 1:t + 1 + cfg.horizon], y[t], t)
                fallbacks += int(result.fallback)
                u_k = result.u + cfg.noise_std * rng.standard_normal(fam.n_u)
            u_k, _ = plant.saturate(u_k)
            y_k = plant.step(u_k)
            if plant.diverged:
                escapes += 1
                break
            u[k], y[k] = u_k, y_k
            n = k
        if n:
            out.append(Trajectory(np.arange(1, n + 1), u[1:n + 1], y[1:n + 1]))
    return out, fallbacks, escapes


TANK_MODEL = NssmConfig(n_u=2, n_y=2, history=3, loss_horizon=3, hidden=(16,), n_z=4)
TANK_NORM = Normalisation([5.0, 5.0], [3.0, 3.0], [6.0, 6.0], [2.0, 2.0])


@pytest.mark.parametrize('case', ['vanderpol', 'escapes', 'quadruple_tank'])
def test_the_data_are_those_of_the_old_tick_loop_bit_for_bit(case):
    """The collector runs the controller's tick (closed_loop.run_episode on a ControllerCore);
    its data must stay those of its own former tick loop, bit for bit, over calls (the seed
    of each episode), escapes, two inputs and two tracked outputs, so that no meta-training
    result changes. Offset-free tracking is on (the MpcConfig default) in both."""
    model, norm, source, theta, config = TINY, NORM, SOURCE, 0.5, CONFIG
    if case == 'escapes':
        source, theta = replace(SOURCE, state_bound=1.5), 1.0
    elif case == 'quadruple_tank':
        model, norm, theta = TANK_MODEL, TANK_NORM, (0.4, 0.7)
        source = SourceConfig(family='quadruple_tank')
        config = replace(CONFIG, ref_bound=2.0, ref_hold_s=20.0)
    collector = OnlineCollector(Nssm(model, norm), config, source)
    fallbacks = escapes = 0
    for call, task in enumerate((3, 3, 1)):
        params = init_params(model, call)
        trajs = collector(task, theta, params)
        ref, f, e = _reference_old_tick_loop(collector, task, theta, params, call)
        fallbacks, escapes = fallbacks + f, escapes + e
        assert len(trajs) == len(ref) > 0
        for a, b in zip(trajs, ref):
            assert np.array_equal(a.steps, b.steps)
            assert np.array_equal(a.u, b.u) and np.array_equal(a.y, b.y)
    stats = collector.stats
    assert (stats.mpc_fallbacks, stats.escaped) == (fallbacks, escapes)
    assert (escapes > 0) == (case == 'escapes')


def test_the_collector_has_no_wall_clock_cap():
    """A simulated episode waits for nothing: OSQP's time limit is off (a cap that trips on a
    loaded machine made a solve a fallback and the source data depend on the load)."""
    assert OnlineCollector(Nssm(TINY, NORM), CONFIG, SOURCE)._mpc_config.time_limit == \
        NO_TIME_LIMIT
