"""Meta-training on the source set where the free latent A diverged stays stable.

The experiment's seed 3 (source set 3, iMAML at the request that was the default then,
:data:`DIVERGED_WITH`): with A free, the spectral radius of A crossed 1 by outer step 40, the
meta-test loss went from 0.14 to 2.9 at step 40 and 168 at step 60 (measured before the stable
parameterisation). With ``stable_latent`` (the default) the loss must stay finite and below 1.0
over the same steps.
"""
import os
from dataclasses import replace

import numpy as np
import torch

from metampc_bringup.experiment_config import learner_config, load
from metampc_model.nssm import Nssm
from metampc_learner.data import normalisation_from, simulate_source, SourceSet
from metampc_learner.meta_train import meta_train

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SOURCE_SET = 3
STEPS = 60
LOSS_BOUND = 1.0     # free A: 2.9 at step 40, 168 at step 60
# the iMAML request of config/default.yaml when the free A diverged (before the re-tune on the
# stable model); pinned so that the test keeps measuring that case
DIVERGED_WITH = {'batch_size': 16, 'inner_steps': 10, 'lr_inner': 0.05, 'gamma': 3.0,
                 'lr_outer': 0.005, 'cg_steps': 5}


def test_imaml_on_the_diverging_source_set_keeps_a_stable_and_the_loss_bounded():
    torch.set_num_threads(1)
    experiment = load(os.path.join(ROOT, 'config', 'default.yaml'))
    cfg = learner_config(experiment, SOURCE_SET)
    assert cfg.nssm.stable_latent
    data = simulate_source(cfg.source)
    model = Nssm(cfg.nssm, normalisation_from([t for ts in data.trajectories for t in ts]))
    source = SourceSet(data, model.norm, cfg.nssm, cfg.train_fraction)
    # the stable A alone: without the anchor of the meta-model (config/default.yaml's w)
    config = replace(cfg.meta, method='imaml', iterations=STEPS, init_loss_weight=0.0,
                     **DIVERGED_WITH)
    result = meta_train(model, source, config)
    losses = np.array(result.losses)
    assert len(losses) == STEPS and result.skipped == 0
    assert np.all(np.isfinite(losses)) and losses.max() < LOSS_BOUND
    assert losses[-10:].mean() < losses[:10].mean()
    a = result.params['A'].double()
    assert float(torch.linalg.eigvals(a).abs().max()) <= cfg.nssm.rho_max
    assert float(torch.linalg.matrix_norm(a, ord=2)) <= cfg.nssm.rho_max
