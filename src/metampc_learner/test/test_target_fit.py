"""The one adaptation entry (target_fit.fit_target): each method is its core on the same
windows, the gain check refuses a model whose gain has the wrong sign and flies the ARX of
its samples in its place, a feature NARX is adapted as narx_learning adapts it, and an ARX
that cannot be written is one FitError (and leaves the gain check unchecked)."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from metampc_learner import narx_learning
from metampc_learner.adapt import adapt, supervised
from metampc_learner.arx import arx_nssm
from metampc_learner.data import simulate_target, Windows
from metampc_learner.learner_params import AdaptJob, fit_settings, PARAMETERS, parse_params
from metampc_learner.oracle import fit_oracle
from metampc_learner.target_fit import ARX, FitError, fit_target, LEAST_SQUARES, ORACLE, \
    SUPERVISED
from metampc_model.feature_narx import FeatureNarx, init_params as narx_params
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params, Nssm, prediction_loss

torch.set_num_threads(1)
TINY = {'history': 3, 'loss_horizon': 3, 'hidden': [16], 'n_z': 3, 'oracle_batch': 16,
        'episode_samples': 40, 'seed': 5}


def _setup(**overrides):
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    values.update({**TINY, **overrides})
    cfg = parse_params(values)
    train = simulate_target(0.4, cfg.source, 60, seed=1)
    held = simulate_target(0.4, cfg.source, 30, seed=2)
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(2), np.ones(2))
    return cfg, Nssm(cfg.nssm, norm), train, held


def _equal(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_each_method_is_its_core_on_the_same_windows():
    cfg, model, train, held = _setup()
    settings = fit_settings(cfg, AdaptJob('maml', 3, 0.05, 0.5, 0))
    windows = [Windows.from_trajectories(p, model.norm, model.config) for p in (train, held)]
    start = init_params(model.config, 9)
    ours = fit_target('maml', model, start, train, held, settings)
    theirs = adapt(model, start, *windows, settings.adapt)
    assert settings.adapt.gamma == 0.5 and ours.steps == 3 and ours.model is model
    assert _equal(ours.result.params, theirs.params)
    assert ours.result.heldout_loss == theirs.heldout_loss
    assert (ours.train_loss, ours.heldout_loss) == (theirs.train_loss[-1],
                                                    theirs.heldout_loss[-1])
    assert (ours.gain_check, ours.replaced_by, ours.rule) == ('', '', '')
    ours = fit_target(SUPERVISED, model, None, train, held, settings)
    theirs = supervised(model, *windows, settings.adapt, cfg.meta.seed)
    assert _equal(ours.result.params, theirs.params)
    oracle = replace(settings, oracle=replace(settings.oracle, steps=4))
    ours = fit_target(ORACLE, model, None, train, held, oracle)
    theirs = fit_oracle(model, init_params(model.config, cfg.meta.seed), *windows,
                        oracle.oracle, cfg.meta.seed)
    assert _equal(ours.result.params, theirs.params) and ours.steps == 4
    ours = fit_target(ARX, model, None, train, held, settings)
    config, norm, params = arx_nssm(train, cfg.arx_order, model.config, model.norm)
    assert ours.model.config == config and _equal(ours.result.params, params)
    with torch.no_grad():
        loss = float(prediction_loss(ours.model, params, *(
            lambda w: (w.u, w.y))(Windows.from_trajectories(held, norm, config))))
    assert ours.heldout_loss == loss and ours.steps == 0 and len(ours.result.train_loss) == 1


def test_the_gain_check_flies_the_arx_in_place_of_a_model_of_the_wrong_sign():
    """One tracked output: negating B negates the model's gain, so of a model and its
    negation (0 steps: each as it is) exactly one agrees in sign with the ARX of the samples;
    the other is refused, and the ARX that the arx method fits flies, with 0 steps and the
    adaptation's curves."""
    cfg, model, train, held = _setup(gain_check=True)
    settings = fit_settings(cfg, AdaptJob('imaml', 0, 0.05, 0.0, 0))
    start = init_params(model.config, 3)
    fits = [fit_target('imaml', model, {**start, 'B': sign * start['B']}, train, held,
                       settings) for sign in (1.0, -1.0)]
    assert sorted(f.replaced_by for f in fits) == ['', ARX]
    kept, refused = sorted(fits, key=lambda f: f.replaced_by)
    assert kept.gain_check.startswith('gain check passed') and kept.model is model
    assert 'disagrees in sign' in refused.gain_check
    arx = fit_target(ARX, model, None, train, held, settings)
    assert refused.model.config == arx.model.config
    assert _equal(refused.result.params, arx.result.params)
    assert (refused.train_loss, refused.heldout_loss, refused.steps) == (
        arx.train_loss, arx.heldout_loss, 0)
    assert refused.result.heldout_loss != arx.result.heldout_loss     # the adaptation's curve
    unchecked = fit_target('imaml', model, start, train, held,
                           replace(settings, gain_check=False))
    assert unchecked.gain_check == '' and unchecked.model is model


def test_an_arx_it_cannot_write_is_one_fit_error_and_leaves_the_gain_check_unchecked():
    cfg, model, train, held = _setup(gain_check=True, arx_order=4)
    settings = fit_settings(cfg, AdaptJob('imaml', 1, 0.05, 0.0, 0))
    with pytest.raises(FitError, match=r'^arx: ARX\(4\) reads 4 samples; the model history H '
                                       r'is 3$'):
        fit_target(ARX, model, None, train, held, settings)
    fitted = fit_target('imaml', model, init_params(model.config, 3), train, held, settings)
    assert fitted.gain_check == ('gain check: unchecked, the ARX: ARX(4) reads 4 samples; the '
                                 'model history H is 3') and fitted.replaced_by == ''


def test_a_feature_narx_is_adapted_as_narx_learning_adapts_it():
    cfg, _, train, held = _setup(model_class='feature_narx', narx_features=4,
                                 narx_hidden=[8], narx_horizon=4)
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(2), np.ones(2))
    meta = FeatureNarx(cfg.narx, norm, narx_params(cfg.narx, 0))
    records, held_records = ([(t.u, t.y) for t in part] for part in (train, held))
    settings = fit_settings(cfg, AdaptJob('imaml', 0, 0.0, 0.02, 0))
    ours = fit_target('imaml', meta, None, train, held, settings)
    theirs = narx_learning.adapt(meta, records, 0.02)
    assert settings.narx_gamma == 0.02 and ours.rule == theirs.rule
    assert torch.equal(ours.model.params['head'], theirs.model.params['head'])
    assert ours.result.heldout_loss == [narx_learning.heldout_loss(m, held_records, 4)
                                        for m in (meta, theirs.model)]
    assert ours.train_loss == narx_learning.one_step_loss(theirs.model, records)
    arx = fit_target(ARX, meta, None, train, held, settings)
    assert arx.rule == LEAST_SQUARES and torch.equal(
        arx.model.params['head'], narx_learning.arx_model(meta, records).params['head'])
    assert fit_settings(cfg, AdaptJob('imaml', 0, 0.0, 0.0, 0)).narx_gamma == \
        cfg.narx_meta.gamma
