"""LearnerSession (the learner node without ROS) on a tiny configuration."""
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from metampc_model.nssm import init_params, Nssm
from metampc_learner.adapt import adapt, AdaptConfig, supervised
from metampc_learner.arx import arx_nssm
from metampc_learner.checkpoint import load_checkpoint, save_checkpoint
from metampc_learner.data import (normalisation_from, simulate_source, simulate_target,
                                  Windows)
from metampc_learner import narx_learning
from metampc_learner.learner_params import (AdaptJob, parse_params, PARAMETERS, ParameterError,
                                            resolve_narx_request)
from metampc_learner.learner_session import LearnerError, LearnerSession
from metampc_learner.oracle import fit_oracle, oracle_data
from metampc_learner.target_buffer import split_target, TargetSamples
from metampc_model.weights_codec import DecodedNarx, model_from_fields
from metampc_plant.plant_description import PlantDescription

torch.set_num_threads(1)
TINY = {'n_systems': 4, 'episodes_per_system': 1, 'episode_samples': 40, 'history': 3,
        'loss_horizon': 3, 'hidden': [16], 'n_z': 3, 'batch_size': 2, 'inner_steps': 2,
        'cg_steps': 2, 'windows_per_task': 8, 'iterations': 12, 'target_buffer_size': 40,
        'heldout_fraction': 0.25, 'adapt_steps': 4, 'oracle_episodes': 3, 'oracle_steps': 15,
        'oracle_batch': 32, 'online_samples': 20, 'online_horizon': 5, 'seed': 2}
PLANT = PlantDescription(family='vanderpol', theta=(0.4,), dt=0.1, substeps=10, u_min=(-1.0,),
                         u_max=(1.0,), n_y=2, lockstep=True, state_bound=10.0)


def _config(**overrides):
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    values.update(TINY)
    values.update(overrides)
    return parse_params(values)


def _target(cfg, n, theta=0.4, seed=1):
    trajs = simulate_target(theta, cfg.source, n, seed=seed)
    return TargetSamples(np.concatenate([t.steps for t in trajs]),
                         np.concatenate([t.u for t in trajs]),
                         np.concatenate([t.y for t in trajs]))


def _equal(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_meta_train_numbers_saves_and_reproduces(tmp_path):
    cfg = _config(checkpoint_dir=str(tmp_path / 'ckpt'))
    session = LearnerSession(cfg)
    reports = []
    out = session.meta_train(cfg.meta, False, reports.append)
    rec = out.record
    assert (rec.version, rec.stage, rec.method) == (1, 'meta', 'imaml')
    assert (rec.seed, rec.train_steps) == (2, 12)
    assert session.latest == {'nssm': 'imaml'} and session.by_class['nssm']['imaml'] is rec
    assert len(out.losses) == 12 and out.final_loss == np.mean(out.losses[-10:])
    assert [r.iteration for r in reports] == list(range(1, 13))
    assert out.collection is None and out.collected_samples == 0
    data = simulate_source(cfg.source)
    assert rec.train_samples == sum(len(t) for ts in data.trajectories for t in ts)
    assert np.array_equal(rec.model.norm.y_std, normalisation_from(
        [t for ts in data.trajectories for t in ts]).y_std)

    ckpt = load_checkpoint(str(tmp_path / 'ckpt' / 'meta_imaml_v1.pt'))
    assert _equal(ckpt.params, rec.params)
    assert ckpt.info == {'method': 'imaml', 'stage': 'meta', 'version': 1,
                         'train_loss': out.final_loss, 'train_steps': 12,
                         'train_samples': rec.train_samples, 'seed': 2, 'dt': 0.1}
    again = LearnerSession(_config()).meta_train(cfg.meta, False).record
    assert _equal(again.params, rec.params), 'same seed, same weights'


def test_adapt_methods_match_the_cores_on_the_same_split(tmp_path):
    cfg = _config()
    session = LearnerSession(cfg)
    job = AdaptJob('', 4, 0.05, 0.0, 0)
    with pytest.raises(LearnerError, match='no meta-model yet: call meta_train first'):
        session.adapt(job, _target(cfg, 40), None)
    meta = session.meta_train(replace(cfg.meta, method='maml'), False).record
    with pytest.raises(LearnerError,
                       match=r"no nssm meta-model for method 'imaml' \(have: maml\)"):
        session.adapt(AdaptJob('imaml', 4, 0.05, 0.0, 0), _target(cfg, 40), None)
    with pytest.raises(LearnerError, match='too few target samples: 12 buffered, 12 used, of '
                                           'which 9 valid for training and 3 held out'):
        session.adapt(job, _target(cfg, 12), None)
    # 40 samples with every 5th lost: 32 buffered, but no run of H + T = 6: the message says so.
    full = _target(cfg, 40)
    keep = np.arange(len(full.steps)) % 5 != 4
    gappy = TargetSamples(full.steps[keep], full.u[keep], full.y[keep])
    with pytest.raises(LearnerError, match=r'32 buffered.*the longest runs are 4 and 4 samples, '
                                           r'broken by \d+ gap\(s\): steps that never reached'):
        session.adapt(job, gappy, None)

    samples = _target(cfg, 40)
    out = session.adapt(job, samples, None)
    assert (out.record.version, out.record.stage, out.record.method) == (2, 'adapted', 'maml')
    assert (out.used_samples, out.train_samples, out.heldout_samples) == (40, 30, 10)
    train, held, _ = split_target(samples, 0, 0.25, 10.0)
    model = meta.model
    windows = [Windows.from_trajectories(p, model.norm, model.config) for p in (train, held)]
    direct = adapt(model, meta.params, *windows, AdaptConfig(4, 0.05, 0.0))
    assert _equal(out.record.params, direct.params)
    assert out.result.heldout_loss == direct.heldout_loss and len(direct.heldout_loss) == 5
    assert out.record.train_loss == direct.train_loss[-1]

    out = session.adapt(AdaptJob('supervised', 4, 0.05, 1.0, 28), samples, None)
    assert (out.record.version, out.record.method, out.used_samples) == (3, 'supervised', 28)
    train, held, _ = split_target(samples, 28, 0.25, 10.0)
    fresh = Nssm(cfg.nssm, meta.model.norm)   # the source normalisation, as every method's
    windows = [Windows.from_trajectories(p, fresh.norm, fresh.config) for p in (train, held)]
    direct = supervised(fresh, *windows, AdaptConfig(4, 0.05, 0.0), seed=cfg.meta.seed)
    assert _equal(out.record.params, direct.params)


def test_the_node_step_rule_reaches_the_adaptation_and_the_loop():
    """adapt_rule gauss_newton (and its adapt_cg_steps) is what the Adapt answer and an
    adaptation in the loop run: equal to the core's, and not the gradient steps'."""
    cfg = _config(adapt_rule='gauss_newton', adapt_cg_steps=5)
    session = LearnerSession(cfg)
    meta = session.meta_train(replace(cfg.meta, method='maml'), False).record
    samples = _target(cfg, 40)
    out = session.adapt(AdaptJob('', 3, 0.05, 0.0, 0), samples, None)
    train, held, _ = split_target(samples, 0, 0.25, 10.0)
    model = meta.model
    windows = [Windows.from_trajectories(p, model.norm, model.config) for p in (train, held)]
    rule = AdaptConfig(3, 0.05, 0.0, 'gauss_newton', 5)
    assert _equal(out.record.params, adapt(model, meta.params, *windows, rule).params)
    assert not _equal(out.record.params,
                      adapt(model, meta.params, *windows, AdaptConfig(3, 0.05, 0.0)).params)
    loop = session.loop_adapt(out.record.version, samples)
    every, _, _ = split_target(samples, 0, 0.0, 10.0)
    direct = adapt(model, out.record.params, Windows.from_trajectories(every, model.norm,
                                                                       model.config),
                   Windows.from_trajectories([], model.norm, model.config),
                   AdaptConfig(cfg.loop.steps, cfg.loop.lr or cfg.adapt.lr, cfg.loop.gamma,
                               'gauss_newton', 5), anchor=meta.params)
    assert _equal(loop.record.params, direct.params)


def test_oracle_fits_simulated_target_episodes():
    cfg = _config()
    session = LearnerSession(cfg)
    job = AdaptJob('oracle', 15, 3e-3, 0.0, 0)
    samples = _target(cfg, 40)
    with pytest.raises(LearnerError, match="the oracle needs the target's theta"):
        session.adapt(job, samples, None)
    with pytest.raises(LearnerError, match='the plant samples at dt = 0.05 s'):
        session.adapt(job, samples, replace(PLANT, dt=0.05))
    out = session.adapt(job, samples, PLANT)
    assert (out.record.method, out.record.stage, out.heldout_samples) == ('oracle', 'adapted', 10)
    episodes = oracle_data(PLANT.theta, cfg.source, cfg.oracle.episodes, cfg.meta.seed)
    assert out.train_samples == sum(len(t) for t in episodes) > 0
    model = Nssm(cfg.nssm, out.record.model.norm)
    _, held, _ = split_target(samples, 0, 0.25, 10.0)
    direct = fit_oracle(model, init_params(cfg.nssm, cfg.meta.seed),
                        Windows.from_trajectories(episodes, model.norm, model.config),
                        Windows.from_trajectories(held, model.norm, model.config),
                        replace(cfg.oracle, steps=15, lr=3e-3), cfg.meta.seed)
    assert _equal(out.record.params, direct.params)
    assert out.result.train_loss[-1] < out.result.train_loss[0]


def test_online_collection_grows_the_source_up_to_the_cap():
    cfg = _config(online_max_samples=100, iterations=3)
    out = LearnerSession(cfg).meta_train(cfg.meta, True)
    stats = out.collection
    assert stats.calls == 3 * 2 - out.skipped and stats.episodes == stats.calls
    assert stats.samples > 100, 'enough collected to hit the cap'
    assert out.collected_samples <= 100
    assert out.collected_samples + out.dropped_samples == stats.samples


def test_versions_continue_after_the_checkpoints_on_disk(tmp_path):
    cfg = _config(checkpoint_dir=str(tmp_path))
    rec = LearnerSession(cfg).meta_train(cfg.meta, False).record
    # As if an earlier run had got to version 7.
    save_checkpoint(str(tmp_path / 'adapted_maml_unrolled_v7.pt'), rec.model, rec.params)
    (tmp_path / 'notes_v99.txt').write_text('not a checkpoint')
    second = LearnerSession(cfg)
    assert second.version == 7
    loaded = second.load_meta(str(tmp_path / 'meta_imaml_v1.pt'))
    assert (loaded.version, loaded.stage, loaded.method) == (8, 'meta', 'imaml')
    assert load_checkpoint(str(tmp_path / 'meta_imaml_v8.pt')).info['dt'] == 0.1
    assert _equal(load_checkpoint(str(tmp_path / 'meta_imaml_v8.pt')).params, rec.params)
    assert second.latest == {'nssm': 'imaml'}


def test_load_meta_refuses_what_is_not_a_meta_model(tmp_path):
    session = LearnerSession(_config())
    with pytest.raises(LearnerError, match="cannot load meta-model '/nonexistent.pt'"):
        session.load_meta('/nonexistent.pt')
    model = Nssm(_config().nssm)
    path = str(tmp_path / 'oracle.pt')
    save_checkpoint(path, model, model.params(), {'method': 'oracle'})
    with pytest.raises(LearnerError, match="holds a 'oracle' model, not a meta-model"):
        session.load_meta(path)
    save_checkpoint(path, model, model.params(), {'method': 'maml', 'dt': 0.05})
    with pytest.raises(LearnerError, match="holds a model of dt = 0.05 s; this learner "
                                           "samples at dt = 0.1 s"):
        session.load_meta(path)
    assert session.version == 0 and not session.by_class


def test_arx_is_fitted_on_the_training_part_and_refused_with_the_reason():
    cfg = _config()
    session = LearnerSession(cfg)
    samples = _target(cfg, 40)
    out = session.adapt(AdaptJob('arx', 4, 0.05, 1.0, 0), samples, None)
    rec = out.record
    assert (rec.method, rec.stage, rec.train_steps) == ('arx', 'adapted', 0)
    assert rec.model.config.n_z == 5          # p (n_y + n_u) - n_u, p = 2
    train, held, _ = split_target(samples, 0, 0.25, 10.0)
    scale = session._fresh_model().norm            # the source stds, as every method's
    config, norm, params = arx_nssm(train, 2, cfg.nssm, scale)
    assert config == rec.model.config and _equal(rec.params, params)
    np.testing.assert_array_equal(rec.model.norm.y_std, scale.y_std)
    assert len(out.result.heldout_loss) == 1 and np.isfinite(out.result.heldout_loss[0])
    deep = LearnerSession(_config(arx_order=4))
    with pytest.raises(LearnerError, match='arx: ARX.4. reads 4 samples; the model history H '
                                           'is 3'):
        deep.adapt(AdaptJob('arx', 0, 0.0, 0.0, 0), samples, None)


def test_the_gain_check_flies_the_arx_in_place_of_a_model_of_the_wrong_sign(monkeypatch):
    """gain_check: an adapted model whose gain on the tracked output has the sign of the ARX
    of its samples is published; negated (its B times -1) it is refused and the ARX that
    Adapt(method='arx') fits on the same samples flies in its place, under the method's name;
    the loop adapts that model from itself."""
    import metampc_learner.target_fit as fit_module
    from metampc_learner.gain_check import gain_verdict
    from metampc_model.predictor import NssmPredictor
    cfg = _config(gain_check=True)
    session = LearnerSession(cfg)
    meta = session.meta_train(replace(cfg.meta, method='maml'), False).record
    samples = _target(cfg, 40)
    arx = session.adapt(AdaptJob('arx', 0, 0.0, 0.0, 0), samples, None)
    assert (arx.gain_check, arx.replaced_by) == ('', '')           # the ARX is not checked

    def latent(model, params):
        return NssmPredictor(model.config, model.norm, params).latent
    train, held, _ = split_target(samples, 0, 0.25, 10.0)
    windows = [Windows.from_trajectories(p, meta.model.norm, meta.model.config)
               for p in (train, held)]
    plain = adapt(meta.model, meta.params, *windows, AdaptConfig(4, 0.05, 0.0))
    sign = np.sign(gain_verdict(latent(meta.model, plain.params),
                                latent(arx.record.model, arx.record.params), [0]).eigs.real[0])

    def signed(factor):
        def adapted(*args, **kwargs):
            result = adapt(*args, **kwargs)
            return replace(result, params={**result.params, 'B': factor * result.params['B']})
        return adapted
    monkeypatch.setattr(fit_module, 'adapt', signed(sign))
    kept = session.adapt(AdaptJob('', 4, 0.05, 0.0, 0), samples, None)
    assert kept.replaced_by == '' and kept.gain_check.startswith('gain check passed')
    assert torch.equal(kept.record.params['B'], sign * plain.params['B'])
    assert kept.record.model.config == meta.model.config

    monkeypatch.setattr(fit_module, 'adapt', signed(-sign))
    out = session.adapt(AdaptJob('', 4, 0.05, 0.0, 0), samples, None)
    assert out.replaced_by == 'arx' and 'disagrees in sign' in out.gain_check
    assert (out.record.method, out.record.stage) == ('maml', 'adapted')
    assert out.record.model.config == arx.record.model.config
    assert _equal(out.record.params, arx.record.params)
    assert (out.record.train_loss, out.record.train_steps) == (arx.record.train_loss, 0)
    assert out.result.heldout_loss == plain.heldout_loss       # what the adaptation did
    monkeypatch.undo()
    loop = session.loop_adapt(out.record.version, samples)
    assert loop.record.model.config == arx.record.model.config and loop.record.method == 'maml'


# --- model_class feature_narx: meta-training, adaptation, the ARX and the oracle of the class,
# checkpoints, the weights message, and what it refuses.

NARX = {**TINY, 'model_class': 'feature_narx', 'n_systems': 6, 'episode_samples': 60,
        'target_buffer_size': 80, 'narx_features': 6, 'narx_hidden': [8],
        'narx_iterations': 15, 'narx_batch_size': 3, 'narx_windows': 16, 'narx_horizon': 4,
        'oracle_episodes': 4}


def _narx_config(**overrides):
    return _config(**{**NARX, **overrides})


def _request(**fields):
    base = dict(method='', iterations=0, batch_size=0, gamma=0.0, lr_outer=0.0, seed=0,
                online_collection=False)
    return SimpleNamespace(**{**base, **fields})


def test_feature_narx_meta_train_then_adapt_gives_a_model_never_worse_than_the_arx(tmp_path):
    cfg = _narx_config(checkpoint_dir=str(tmp_path))
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
    assert out.rule in ('ridge', 'ridge_to_arx', 'arx', 'arx_validated')
    assert out.record.method == 'imaml'
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
    loaded = LearnerSession(_narx_config()).load_meta(str(tmp_path / 'meta_imaml_v1.pt'))
    assert loaded.model.shape == cfg.narx
    with pytest.raises(LearnerError, match='holds a feature_narx model; this learner trains '
                                           'model_class nssm'):
        LearnerSession(_narx_config(model_class='nssm')).load_meta(
            str(tmp_path / 'meta_imaml_v1.pt'))


def test_what_a_feature_narx_learner_refuses():
    cfg = _narx_config()
    with pytest.raises(ValueError, match="meta-trains with imaml or maml, not 'maml_unrolled'"):
        resolve_narx_request(_request(method='maml_unrolled'), cfg.narx_meta, cfg.meta)
    with pytest.raises(ValueError, match="online collection is the NSSM's only"):
        resolve_narx_request(_request(online_collection=True), cfg.narx_meta, cfg.meta)
    got = resolve_narx_request(_request(method='maml', iterations=3, lr_outer=0.01, gamma=0.5),
                               cfg.narx_meta, cfg.meta)
    assert (got.method, got.iterations, got.lr, got.gamma, got.batch_size) == (
        'maml', 3, 0.01, 0.5, 3)
    got = resolve_narx_request(_request(method='imaml', gamma=0), cfg.narx_meta, cfg.meta)
    assert got.gamma == cfg.narx_meta.gamma
    for name in ('gain_check', 'loop_adaptation', 'online_collection'):
        with pytest.raises(ParameterError, match=f"{name}: the NSSM's only"):
            _narx_config(**{name: True})
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


def test_an_nssm_learner_keeps_a_feature_narx_of_the_same_method_apart():
    """A request may name the other class (an experiment compares both): an NSSM learner
    meta-trains iMAML of each class, and each class's adaptation starts from its own."""
    cfg = _config(**{k: v for k, v in NARX.items() if k != 'model_class'})
    assert cfg.model_class == 'nssm'
    session = LearnerSession(cfg)
    nssm = session.meta_train(cfg.meta, False).record
    narx = session.meta_train(resolve_narx_request(_request(), cfg.narx_meta, cfg.meta),
                              False).record
    assert session.by_class == {'nssm': {'imaml': nssm}, 'feature_narx': {'imaml': narx}}
    samples = _target(cfg, 80)
    own = session.adapt(AdaptJob('imaml', 2, 0.05, 0.0, 0), samples, PLANT)
    other = session.adapt(AdaptJob('imaml', 0, 0.0, 0.0, 0, 'feature_narx'), samples, PLANT)
    assert own.record.model is nssm.model and own.record.model_class == 'nssm'
    assert other.record.model.shape == narx.model.shape and other.rule
    # the node's class before the request's: no NSSM meta-model of maml
    with pytest.raises(LearnerError, match="no nssm meta-model for method 'maml'"):
        session.adapt(AdaptJob('maml', 2, 0.05, 0.0, 0), samples, PLANT)
