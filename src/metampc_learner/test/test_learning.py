"""CI-sized learning check: iMAML-initialised adaptation beats supervised training.

Short meta-training (fixed seeds, ~20 s on 2 cores), then the same 20 gradient steps (lr 0.05)
on 300 samples of each unseen target from the meta-trained weights and from a random
initialisation; held-out target loss after the steps must be lower for iMAML.
"""
import numpy as np
import torch

from metampc_model.nssm import Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.adapt import adapt, AdaptConfig, supervised
from metampc_learner.data import (normalisation_from, simulate_source, simulate_target,
                                  SourceConfig, SourceSet, Windows)
from metampc_learner.meta_train import meta_train, MetaConfig

TARGETS = (-0.4, 0.7, 1.5)    # not among the source systems (continuous thetas)


def test_imaml_adaptation_beats_supervised_on_unseen_targets():
    torch.set_num_threads(1)
    source_config = SourceConfig(n_systems=40, episode_samples=120, seed=0)
    data = simulate_source(source_config)
    assert not set(TARGETS) & set(data.thetas[:, 0].tolist())
    config = NssmConfig(hidden=(64, 64))
    norm = normalisation_from([t for ts in data.trajectories for t in ts])
    model = Nssm(config, norm)
    meta = meta_train(model, SourceSet(data, norm, config),
                      MetaConfig(iterations=120, batch_size=8, inner_steps=5,
                                 windows_per_task=32, lr_outer=3e-3, seed=0))
    assert meta.skipped == 0
    assert np.mean(meta.losses[-10:]) < 0.5 * np.mean(meta.losses[:10])
    steps = AdaptConfig(steps=20, lr=0.05)
    for i, theta in enumerate(TARGETS):
        train = Windows.from_trajectories(simulate_target(theta, source_config, 300, 10 + i),
                                          norm, config)
        held = Windows.from_trajectories(simulate_target(theta, source_config, 300, 20 + i),
                                         norm, config)
        ours = adapt(model, meta.params, train, held, steps)
        base = supervised(model, train, held, steps, seed=1)
        assert ours.heldout_loss[-1] < 0.5 * base.heldout_loss[-1], (theta, ours.heldout_loss,
                                                                     base.heldout_loss)
