"""LearnerSession with model_class feature_narx: meta-training, adaptation, the ARX and the
oracle of the class, checkpoints, the weights message, and what it refuses."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from metampc_model.weights_codec import DecodedNarx, model_from_fields
from metampc_learner import narx_learning
from metampc_learner.checkpoint import load_checkpoint
from metampc_learner.learner_params import (AdaptJob, parse_params, PARAMETERS, ParameterError,
                                            resolve_narx_request)
from metampc_learner.learner_session import LearnerError, LearnerSession
from metampc_learner.target_buffer import split_target, TargetSamples
from test_learner_session import _target, PLANT, TINY

torch.set_num_threads(1)
NARX = {**TINY, 'model_class': 'feature_narx', 'n_systems': 6, 'episode_samples': 60,
        'target_buffer_size': 80, 'narx_features': 6, 'narx_hidden': [8],
        'narx_iterations': 15, 'narx_batch_size': 3, 'narx_windows': 16, 'narx_horizon': 4,
        'oracle_episodes': 4}


def _config(**overrides):
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    values.update(NARX)
    values.update(overrides)
    return parse_params(values)


def _request(**fields):
    base = dict(method='', iterations=0, batch_size=0, gamma=0.0, lr_outer=0.0, seed=0,
                online_collection=False)
    return SimpleNamespace(**{**base, **fields})


def test_meta_train_then_adapt_gives_a_model_never_worse_than_the_arx(tmp_path):
    cfg = _config(checkpoint_dir=str(tmp_path))
    session = LearnerSession(cfg)
    reports = []
    meta = session.meta_train(resolve_narx_request(_request(), cfg.narx_meta, cfg.meta), False,
                              reports.append)
    rec = meta.record
    assert (rec.version, rec.stage, rec.method, rec.train_steps) == (1, 'meta', 'imaml', 15)
    assert [r.iteration for r in reports] == list(range(1, 16))
    assert meta.final_loss == pytest.approx(np.mean(meta.losses[-10:]))
    assert rec.model.shape.features == 6 and rec.model.shape.hidden == (8,)

    samples = _target(cfg, 80)
    out = session.adapt(AdaptJob('imaml', 20, 0.05, 0.0, 0), samples, PLANT)
    arx = session.adapt(AdaptJob('arx', 20, 0.05, 0.0, 0), samples, PLANT)
    train, held, _ = split_target(samples, 0, cfg.heldout_fraction, cfg.source.state_bound)
    records = [(t.u, t.y) for t in train]
    # the training loss is the model's one-step loss on the training part, never above the
    # least-squares ARX(p) of the same samples (published by adapt('arx'))
    assert out.record.train_loss == pytest.approx(
        narx_learning.one_step_loss(out.record.model, records), rel=1e-12)
    assert out.record.train_loss <= arx.record.train_loss * (1 + 1e-9)
    assert out.rule in ('ridge', 'least_squares', 'arx') and out.record.method == 'imaml'
    assert len(out.result.heldout_loss) == 2 and len(arx.result.heldout_loss) == 1
    assert out.result.heldout_loss[0] == pytest.approx(narx_learning.heldout_loss(
        rec.model, [(t.u, t.y) for t in held], 4))
    # the ARX is the class's linear model: its feature columns are zero
    n_s = cfg.narx.n_s
    assert torch.all(arx.record.params['head'][:, n_s:n_s + 6] == 0)

    oracle = session.adapt(AdaptJob('oracle', 0, 0.0, -1.0, 0), samples, PLANT)
    assert oracle.record.method == 'oracle' and oracle.train_samples > 80

    # what the node publishes decodes to the same model, and the checkpoint loads back
    decoded = model_from_fields(out.record.fields())
    assert isinstance(decoded, DecodedNarx) and decoded.shape == cfg.narx
    np.testing.assert_allclose(decoded.params['head'], out.record.params['head'].numpy(),
                               rtol=1e-6)
    ckpt = load_checkpoint(str(tmp_path / f'adapted_imaml_v{out.record.version}.pt'))
    assert ckpt.model.shape == cfg.narx and torch.equal(ckpt.params['head'],
                                                        out.record.params['head'])
    loaded = LearnerSession(_config()).load_meta(str(tmp_path / 'meta_imaml_v1.pt'))
    assert loaded.model.shape == cfg.narx
    with pytest.raises(LearnerError, match='holds a feature_narx model; this learner trains '
                                           'model_class nssm'):
        LearnerSession(_config(model_class='nssm')).load_meta(str(tmp_path / 'meta_imaml_v1.pt'))


def test_what_a_feature_narx_learner_refuses():
    cfg = _config()
    with pytest.raises(ValueError, match="meta-trains with imaml or maml, not 'maml_unrolled'"):
        resolve_narx_request(_request(method='maml_unrolled'), cfg.narx_meta, cfg.meta)
    with pytest.raises(ValueError, match="online collection is the NSSM's only"):
        resolve_narx_request(_request(online_collection=True), cfg.narx_meta, cfg.meta)
    got = resolve_narx_request(_request(method='maml', iterations=3, lr_outer=0.01, gamma=0.5),
                               cfg.narx_meta, cfg.meta)
    assert (got.method, got.iterations, got.lr, got.gamma, got.batch_size) == (
        'maml', 3, 0.01, 0.5, 3)
    for name in ('gain_check', 'loop_adaptation', 'online_collection'):
        with pytest.raises(ParameterError, match=f"{name}: the NSSM's only"):
            _config(**{name: True})
    session = LearnerSession(cfg)
    samples = _target(cfg, 80)
    with pytest.raises(LearnerError, match="adapts with '', 'imaml', 'maml', 'arx', 'oracle', "
                                           "not 'supervised'"):
        session.adapt(AdaptJob('supervised', 4, 0.05, 0.0, 0), samples, PLANT)
    with pytest.raises(LearnerError, match='no meta-model yet'):
        session.adapt(AdaptJob('', 4, 0.05, 0.0, 0), samples, PLANT)
    few = TargetSamples(samples.steps[:12], samples.u[:12], samples.y[:12])
    with pytest.raises(LearnerError, match='too few target samples: 12 buffered'):
        session.adapt(AdaptJob('arx', 4, 0.05, 0.0, 0), few, PLANT)
