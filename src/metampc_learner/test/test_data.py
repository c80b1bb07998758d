"""Data sets: windows never span gaps or escapes, non-finite data never enters, splits, caps."""
import dataclasses

import numpy as np
import pytest
import torch

from metampc_model.nssm_config import NssmConfig
from metampc_learner.data import (longest_run, normalisation_from, samples_in,
                                  simulate_episodes, simulate_source,
                                  simulate_target, SourceConfig, SourceData, SourceSet,
                                  split_by_time, Trajectory, trajectories_from_samples,
                                  Windows, windows)
from metampc_plant.family import ThetaComponent
from metampc_plant.registry import get_family, register

SMALL = NssmConfig(history=3, loss_horizon=4, hidden=(8,))
VDP = get_family('vanderpol')


def vdp_variant(name: str, x0_bound: float, theta=None) -> str:
    """Register van der Pol with initial states in [-x0_bound, x0_bound]^2 (and another
    Theta); return its name."""
    register(dataclasses.replace(VDP, name=name, x0_low=(-x0_bound,) * 2,
                                 x0_high=(x0_bound,) * 2, theta=theta or VDP.theta))
    return name


def _traj(start, n, value=0.0):
    steps = np.arange(start, start + n)
    return Trajectory(steps, np.full(n, value), np.stack([steps, -steps], axis=1) * 1.0)


def test_trajectory_rejects_gaps_and_non_finite():
    with pytest.raises(ValueError, match='consecutive'):
        Trajectory([1, 2, 4], np.zeros(3), np.zeros((3, 2)))
    with pytest.raises(ValueError, match='non-finite'):
        Trajectory([1, 2, 3], [0.0, np.inf, 0.0], np.zeros((3, 2)))


def test_buffered_samples_split_at_gaps_non_finite_and_bound():
    steps = np.array([5, 1, 2, 3, 4, 6, 7, 9, 10, 11, 12, 13, 14, 3])    # unsorted, gap, dup
    u = np.zeros(14)
    y = np.ones((14, 2))
    y[6] = np.nan        # step 7
    y[10, 0] = 50.0      # step 12 beyond the bound
    trajs = trajectories_from_samples(steps, u, y, state_bound=10.0)
    assert [t.steps.tolist() for t in trajs] == [[1, 2, 3, 4, 5, 6], [9, 10, 11], [13, 14]]
    for t in trajs:
        assert np.all(np.isfinite(t.y)) and np.abs(t.y).max() <= 10.0
    assert trajectories_from_samples([], np.zeros(0), np.zeros((0, 2))) == []
    assert (samples_in(trajs), longest_run(trajs)) == (11, 6)
    assert (samples_in([]), longest_run([])) == (0, 0)


def test_windows_stay_inside_one_trajectory():
    trajs = trajectories_from_samples(np.r_[0:10, 12:20], np.zeros(18),
                                      np.arange(18.0)[:, None] * [1, 1])
    u, y = windows(trajs, 5)
    assert u.shape == (6 + 4, 5, 1) and y.shape == (10, 5, 2)
    # every window is a run of consecutive buffered samples (y holds the buffer index)
    assert np.all(np.diff(y[:, :, 0], axis=1) == 1)
    assert windows(trajs, 11)[0].shape == (0, 11, 1)


def test_split_by_time_is_disjoint():
    first, second = split_by_time([_traj(0, 10), _traj(100, 7)], 0.5)
    assert [t.steps.tolist() for t in first] == [list(range(5)), [100, 101, 102, 103]]
    assert [t.steps.tolist() for t in second] == [list(range(5, 10)), [104, 105, 106]]


def test_escaping_episode_never_produces_a_window():
    config = SourceConfig(family=vdp_variant('vdp_x0_3', 3.0), episode_samples=150,
                          state_bound=5.0)
    thetas = np.full(40, -1.0)   # unstable limit cycle; x0 up to 3 lies outside it
    episodes, escaped = simulate_episodes(thetas, config, seed=3)
    assert escaped > 0, 'the set-up must produce escapes'
    assert sum(t is None for t in episodes) == escaped
    kept = [t for t in episodes if t is not None]
    for t in kept:
        assert np.abs(t.y).max() <= 5.0 and len(t) == 150
    u, y = windows(kept, SMALL.window)
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(y)) and np.abs(y).max() <= 5.0
    assert len(u) == len(kept) * (150 - SMALL.window + 1)


def test_source_set_from_escaping_systems():
    unstable = (ThetaComponent('theta', '', 'damping', 'normal', -1.5, 0.2),)
    config = SourceConfig(family=vdp_variant('vdp_unstable', 2.5, unstable), n_systems=30,
                          episodes_per_system=1, episode_samples=120, state_bound=5.0, seed=4)
    data = simulate_source(config)
    assert data.escaped > 0
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    source = SourceSet(data, norm, SMALL)
    assert len(source) + len(source.left_out) == 30
    assert len(source.left_out) == data.escaped
    train, test = source.sample(range(len(source)), 8, np.random.default_rng(0))
    for w in (train, test):
        assert torch.isfinite(w.u).all() and torch.isfinite(w.y).all()


def test_source_set_sampling_is_seeded_and_shaped():
    data = simulate_source(SourceConfig(n_systems=6, episode_samples=60, seed=1))
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    source = SourceSet(data, norm, SMALL, dtype=torch.float64)
    a = source.sample([0, 3, 3], 5, np.random.default_rng(7))
    b = source.sample([0, 3, 3], 5, np.random.default_rng(7))
    assert a[0].u.shape == (3, 5, SMALL.window, 1) and a[1].y.shape == (3, 5, SMALL.window, 2)
    assert a[0].u.dtype == torch.float64
    assert all(torch.equal(x.u, y.u) and torch.equal(x.y, y.y) for x, y in zip(a, b))


def test_normalisation_from_source():
    trajs = [Trajectory(np.arange(4), [1.0, 3.0, 1.0, 3.0],
                        [[0.0, 1.0], [2.0, 1.0], [0.0, 1.0], [2.0, 1.0]])]
    norm = normalisation_from(trajs, y_spread=3.0)
    assert np.allclose(norm.u_mean, [2.0]) and np.allclose(norm.u_std, [1.0])
    assert np.allclose(norm.y_mean, [1.0, 1.0]) and np.allclose(norm.y_std, [3.0, 3.0])
    w = Windows.from_trajectories(trajs, norm, NssmConfig(history=2, loss_horizon=1))
    assert w.u.shape == (2, 3, 1) and torch.allclose(w.u[0, :, 0], torch.tensor([-1., 1, -1]))


def test_collected_data_is_capped_oldest_first():
    data = SourceData(np.array([[0.5], [1.0]]), [[_traj(0, 40)], [_traj(0, 40, 1.0)]], 0)
    norm = normalisation_from([_traj(0, 40), _traj(0, 40, 1.0)])
    source = SourceSet(data, norm, SMALL, max_collected=50)
    base = len(source._tasks[0][0])
    source.add(0, [_traj(1000, 20, 5.0)])
    source.add(1, [_traj(2000, 20, 6.0)])
    assert source.collected_samples == 40 and source.dropped_samples == 0
    assert len(source._tasks[0][0]) == base + 10 - SMALL.window + 1
    source.add(0, [_traj(3000, 20, 7.0)])        # 60 > 50: the first collection goes
    assert source.collected_samples == 40 and source.dropped_samples == 20
    inputs = torch.unique(source._tasks[0][0].u * norm.u_std[0] + norm.u_mean[0]).tolist()
    assert 5.0 not in [round(v, 6) for v in inputs] and 7.0 in [round(v, 6) for v in inputs]


def test_target_set_has_the_requested_bounded_samples():
    config = SourceConfig(episode_samples=120)
    for theta in (-0.8, 0.3, 2.0):
        trajs = simulate_target(theta, config, n_samples=300, seed=2)
        assert sum(len(t) for t in trajs) == 300
        assert all(np.abs(t.y).max() <= VDP.state_bound for t in trajs)
    again, other = simulate_target(0.3, config, 300, seed=2), simulate_target(0.3, config, 300, 3)
    assert [t.steps[0] for t in again] == [1, 1, 1]
    assert all(np.array_equal(a.u, b.u) and np.array_equal(a.y, b.y)
               for a, b in zip(again, simulate_target(0.3, config, 300, seed=2)))
    assert not np.array_equal(again[0].y, other[0].y)
    with pytest.raises(RuntimeError, match='bounded samples'):
        simulate_target(-3.0, SourceConfig(family=vdp_variant('vdp_x0_4', 4.0), state_bound=4.5),
                        300, max_attempts=3)
