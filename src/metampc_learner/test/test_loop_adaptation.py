"""Adaptation in the loop, the learner's core: the latest samples of an episode, and
LearnerSession.loop_adapt from the model in use, anchored to the meta-model."""
import dataclasses

import numpy as np
import pytest
import torch

from metampc_model.feature_narx import FeatureNarx, init_params as narx_init_params, NarxShape
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params, Nssm
from metampc_model.nssm_config import NssmConfig
from metampc_learner.adapt import adapt, AdaptConfig
from metampc_learner.data import Windows
from metampc_learner.learner_params import LearnerNodeConfig, parse_params, PARAMETERS
from metampc_learner.learner_session import LearnerError, LearnerSession
from metampc_learner.loop_adaptation import LoopConfig, RecentSamples
from metampc_learner.narx_learning import one_step_loss
from metampc_learner.target_buffer import split_target
from metampc_plant.simulator import Plant, PlantConfig


def test_recent_samples_keep_the_latest_of_the_episode_up_to_a_step():
    recent = RecentSamples(5)
    for k in range(12):
        recent.add(k, [0.1 * k], [k, -k], diverged=(k == 9))
    window = recent.until(10, 3)
    assert window.steps.tolist() == [7, 8, 10]      # 9 diverged, 11 after the request
    assert window.y[:, 0].tolist() == [7.0, 8.0, 10.0]
    assert recent.wait_for(11, 0.0) and not recent.wait_for(12, 0.05)
    recent.add(0, [0.0], [0.0, 0.0])    # a reset: a new episode, y_0 not kept
    assert len(recent.until(100, 10)) == 0
    recent.add(1, [np.nan], [0.0, 0.0])     # non-finite: not kept
    recent.add(2, [0.2], [2.0, 2.0])
    assert recent.until(100, 10).steps.tolist() == [2]


def test_a_window_the_plant_no_longer_feeds_is_refused():
    """An escaped plant holds its last finite state and flags every y diverged: the window up
    to a later request is the samples before the escape, the same at every request (before:
    adapted on again and again, window loss 0.1419 -> 0.1419 every 10 s)."""
    rng = np.random.default_rng(0)
    recent = RecentSamples(1100)
    frozen = [3.0, -7.0]
    for k in range(901):
        escaped = k >= 412
        recent.add(k, [0.1], frozen if escaped else rng.normal(size=2), diverged=escaped)
    assert recent.refusal(411, 100) == ''
    assert len(recent.until(900, 100)) == 100      # samples there are: 312..411
    why = recent.refusal(900, 100)
    assert why.startswith('489 of the samples from step 312 to 900 (the first at step 412, '
                          'the last at 900) are diverged or non-finite'), why
    # A non-finite sample inside the window refuses it too; one before the window does not.
    recent.add(0, [0.0], [0.0, 0.0])        # a reset: a new episode
    for k in range(1, 201):
        recent.add(k, [0.1], [np.nan, 0.0] if k == 150 else rng.normal(size=2))
    assert 'the first at step 150' in recent.refusal(200, 100)
    assert recent.refusal(200, 40) == ''
    # A plant whose outputs stopped changing (not flagged): nothing to adapt on.
    recent.add(0, [0.0], [0.0, 0.0])
    for k in range(1, 60):
        recent.add(k, [0.0], [1.0, 2.0])
    assert recent.refusal(59, 50).startswith('the outputs did not change from step 10 to 59')


def test_the_anchor_is_the_proximal_centre():
    """From init psi_0 with the anchor elsewhere, a huge gamma pulls the result to the anchor
    (the data term is negligible); anchor = init is the former adaptation, bit for bit."""
    config = NssmConfig(history=3, loss_horizon=3, hidden=(8,), n_z=2)
    norm = Normalisation(np.zeros(1), np.ones(1), np.zeros(2), np.ones(2))
    model = Nssm(config, norm, seed=0)
    rng = np.random.default_rng(0)
    train = Windows(torch.as_tensor(rng.normal(size=(16, 6, 1)), dtype=torch.float32),
                    torch.as_tensor(rng.normal(size=(16, 6, 2)), dtype=torch.float32))
    init, anchor = init_params(config, 1), init_params(config, 2)
    pulled = adapt(model, init, train, train, AdaptConfig(30, 1e-3, 1e4), anchor=anchor)
    gap = [float((pulled.params[k] - anchor[k]).abs().max()) for k in anchor]
    start = [float((init[k] - anchor[k]).abs().max()) for k in anchor]
    assert max(g / s for g, s in zip(gap, start)) < 0.05
    same = adapt(model, init, train, train, AdaptConfig(5, 0.05, 0.5), anchor=init)
    plain = adapt(model, init, train, train, AdaptConfig(5, 0.05, 0.5))
    assert all(torch.equal(same.params[k], plain.params[k]) for k in init)


def tiny_session() -> LearnerSession:
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    values.update(history=3, loss_horizon=3, hidden=[16], n_z=3, n_systems=4, episode_samples=40,
                  target_buffer_size=60, loop_window=40, loop_steps=5, loop_lr=0.05)
    config = parse_params(values)
    assert isinstance(config, LearnerNodeConfig)
    return LearnerSession(config)


def samples_of(theta, n=60, seed=0):
    plant = Plant(PlantConfig(theta=(theta,), x0=(0.5, 0.0)))
    rng = np.random.default_rng(seed)
    recent = RecentSamples(1000)
    recent.add(0, [0.0], plant.output())
    for k in range(1, n + 1):
        u = [float(rng.uniform(-1, 1))]
        recent.add(k, u, plant.step(u))
    return recent


def test_loop_adapt_starts_from_the_model_in_use_and_lowers_the_window_loss():
    session = tiny_session()
    model = session._fresh_model()
    meta = session._new_record(model=model, params=init_params(model.config, 0),
                               method='imaml', stage='meta', train_loss=0.0, train_steps=0,
                               train_samples=0, seed=0)
    in_use = session._new_record(model=model, params=init_params(model.config, 3),
                                 method='imaml', stage='adapted', train_loss=0.0,
                                 train_steps=0, train_samples=0, seed=0)
    recent = samples_of(-0.5)
    out = session.loop_adapt(in_use.version, recent.until(50, 40))
    assert (out.record.stage, out.record.method, out.record.version) == ('online', 'imaml', 3)
    assert out.train_samples == 40 and out.heldout_samples == 0
    loss = out.result.train_loss
    assert len(loss) == 6 and loss[-1] < loss[0]
    # The same, by hand: adapt from the model in use with the meta-model as the centre.
    train, _, _ = split_target(recent.until(50, 40), 0, 0.0, 1e9)
    windows = Windows.from_trajectories(train, model.norm, model.config)
    again = adapt(model, in_use.params, windows, windows,
                  AdaptConfig(5, 0.05, session.config.loop.gamma), anchor=meta.params)
    assert all(torch.equal(again.params[k], out.record.params[k]) for k in again.params)
    # And then from that model, for the next request.
    assert session.loop_adapt(3, recent.until(60, 40)).record.version == 4


def test_loop_adapt_refuses_what_it_cannot_do():
    session = tiny_session()
    with pytest.raises(LearnerError, match='model version 7 is not one of the last'):
        session.loop_adapt(7, samples_of(0.5).until(50, 40))
    model = session._fresh_model()
    session._new_record(model=model, params=init_params(model.config, 0), method='supervised',
                        stage='adapted', train_loss=0.0, train_steps=0, train_samples=0, seed=0)
    with pytest.raises(LearnerError, match='too few samples: the window holds 5'):
        session.loop_adapt(1, samples_of(0.5).until(5, 40))


@pytest.mark.parametrize('overrides, match', [
    (dict(loop_window=500), 'loop_window: 500 samples'),
    (dict(loop_window=5), 'loop_window: 5 samples'),
    (dict(loop_steps=0), 'loop_steps'),
    (dict(loop_gamma=-1.0), 'loop_gamma'),
])
def test_bad_loop_parameters_are_refused(overrides, match):
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    values.update(overrides)
    with pytest.raises(ValueError, match=match):
        parse_params(values)


def test_loop_config_defaults():
    assert dataclasses.asdict(LoopConfig()) == dict(adaptation=False, window=0, steps=10,
                                                    lr=0.0, gamma=1.0)


def test_a_feature_narx_in_the_loop_is_its_meta_model_adapted_on_the_window():
    """A feature NARX's answer: the meta-model's g, a new head by the closed-form adaptation of
    the meta-model (not of the model in use: two models in use with other features and heads
    get the same answer) that fits the window's one-step equations better than the model in
    use. Fails
    where the NARX goes the NSSM's way (gradient steps on Windows of an Nssm config) or starts
    from the model in use."""
    session = tiny_session()
    shape = NarxShape(1, 2, order=2, features=8, hidden=(8,))
    norm = Normalisation(np.zeros(1), np.full(1, 0.6), np.zeros(2), np.ones(2))
    meta = FeatureNarx(shape, norm, narx_init_params(shape, 0))
    record = dict(method='imaml', train_loss=0.0, train_steps=0, train_samples=0, seed=0)
    session._new_record(model=meta, params=meta.params, stage='meta', **record)
    heads = []
    for seed in (1, 2):         # models in use with features and heads of their own
        params = narx_init_params(shape, seed)
        in_use = session._new_record(model=FeatureNarx(shape, norm, params), params=params,
                                     stage='adapted', **record)
        window = samples_of(-0.5).until(50, 40)
        out = session.loop_adapt(in_use.version, window)
        assert (out.record.stage, out.record.method) == ('online', 'imaml')
        new = out.record.model
        assert all(torch.equal(new.params[k], meta.params[k]) for k in meta.params
                   if k != 'head')
        train, _, _ = split_target(window, 0, 0.0, 1e9)
        records = [(t.u, t.y) for t in train]
        assert (one_step_loss(new, records)
                < 0.5 * one_step_loss(in_use.model, records)), seed
        heads.append(new.params['head'])
    assert torch.equal(heads[0], heads[1])
