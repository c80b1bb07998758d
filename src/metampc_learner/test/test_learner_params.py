"""Learner parameters (declared table -> typed config) and the resolution of service requests."""
from dataclasses import replace
import re

from metampc_msgs.srv import Adapt, MetaTrain
import numpy as np
import pytest

from metampc_model.nssm_config import NssmConfig
from metampc_learner.adapt import AdaptConfig
from metampc_learner.data import SourceConfig, windows
from metampc_learner.learner_params import (AdaptJob, parse_params, ParameterError, PARAMETERS,
                                            request_class, resolve_adapt_request,
                                            resolve_meta_request)
from metampc_learner.meta_train import MetaConfig
from metampc_learner.online_collection import OnlineCollectionConfig
from metampc_learner.oracle import OracleConfig
from metampc_learner.target_buffer import split_target, TargetSamples

NAN, INF = float('nan'), float('inf')


def _raw(**overrides):
    values = {name: spec.default for name, spec in PARAMETERS.items()}
    values.update(overrides)
    return values


def test_the_loss_horizon_was_called_horizon():
    """The NSSM's T is loss_horizon (the MPC's N is the controller's horizon); the former name
    still works for one release (metampc_common.renames)."""
    assert PARAMETERS['loss_horizon'].formerly == 'horizon' and 'horizon' not in PARAMETERS


def test_defaults_are_those_of_the_cores():
    cfg = parse_params(_raw())
    assert cfg.meta == MetaConfig() and cfg.nssm == NssmConfig() and (
        cfg.source == SourceConfig().resolved())
    assert cfg.adapt == AdaptConfig() and cfg.oracle == OracleConfig()
    assert cfg.online == OnlineCollectionConfig()
    assert (cfg.target_buffer_size, cfg.buffer_on_start, cfg.online_collection) == (300, True,
                                                                                    False)
    assert (cfg.meta_model_path, cfg.checkpoint_dir) == ('', '')


def test_values_reach_the_config_and_integers_pass_for_doubles():
    cfg = parse_params(_raw(method='maml', iterations=7, batch_size=3, inner_steps=4, gamma=2,
                            lr_inner=1, lr_outer=0.01, cg_steps=6, curvature='hessian',
                            windows_per_task=5, seed=11, n_z=4, history=6, loss_horizon=7,
                            hidden=[32, 8], n_systems=9, dt=1, u_min=-0.5, u_max=1,
                            excitation='prbs', hold_s=1, source_seed=5,
                            online_collection=True, online_noise_std=0, online_samples=40,
                            target_buffer_size=120, buffer_on_start=False, adapt_steps=3,
                            adapt_gamma=1, oracle_episodes=7, oracle_steps=9,
                            checkpoint_dir='/tmp/x', torch_threads=1, progress_period=1))
    assert cfg.meta == replace(MetaConfig(), method='maml', iterations=7, batch_size=3,
                               inner_steps=4, gamma=2.0, lr_inner=1.0, lr_outer=0.01,
                               cg_steps=6, curvature='hessian', windows_per_task=5, seed=11)
    assert cfg.nssm == NssmConfig(n_z=4, history=6, loss_horizon=7, hidden=(32, 8))
    assert (cfg.source.n_systems, cfg.source.dt, cfg.source.seed) == (9, 1.0, 5)
    exc = cfg.source.excitation
    assert (exc.kind, exc.u_min, exc.u_max, exc.hold_s) == ('prbs', (-0.5,), (1.0,), 1.0)
    region = parse_params(_raw(family='quadruple_tank', excitation_center=[3, 2.5],
                               excitation_amplitude=0.4)).source.excitation
    assert [b.tolist() for b in region.band()] == [[1.0, 0.5], [5.0, 4.5]]    # +- 0.4 x 5 V
    assert cfg.online_collection and cfg.online.noise_std == 0.0 and cfg.online.seed == 11
    assert cfg.online.episode_samples == 40
    assert (cfg.target_buffer_size, cfg.buffer_on_start) == (120, False)
    assert cfg.adapt == AdaptConfig(steps=3, lr=0.05, gamma=1.0)
    assert (cfg.oracle.episodes, cfg.oracle.steps) == (7, 9)
    assert (cfg.checkpoint_dir, cfg.torch_threads, cfg.progress_period) == ('/tmp/x', 1, 1.0)
    assert all(isinstance(v, float) for v in (cfg.meta.gamma, cfg.meta.lr_inner, cfg.source.dt))


@pytest.mark.parametrize('overrides,match', [
    ({'iterations': 0}, 'iterations must be >= 1'),
    ({'batch_size': 2.5}, 'batch_size must be an integer'),
    ({'gamma': 0.0}, 'gamma must be > 0'),
    ({'lr_outer': -1.0}, 'lr_outer must be > 0'),
    ({'dt': NAN}, 'dt must be finite'),
    ({'family': 'tank'}, "unknown plant family 'tank'; installed: cascaded_tanks, duffing"),
    ({'method': 'reptile'}, 'method must be one of imaml, maml, maml_unrolled'),
    ({'curvature': 'fisher'}, 'curvature must be one of gauss_newton, hessian'),
    ({'hidden': [16, 0]}, 'hidden must be >= 1'),
    ({'rho_max': 0.0}, 'rho_max must be > 0'),
    ({'rho_max': -0.5}, 'rho_max must be > 0'),
    ({'consistency_weight': -0.1}, 'consistency_weight must be >= 0'),
    ({'stable_latent': 1}, 'stable_latent must be true or false'),
    ({'hidden': 'wide'}, 'hidden must be a list of integers'),
    ({'hidden': [1.5]}, 'hidden must be an integer'),
    ({'online_collection': 1}, 'online_collection must be true or false'),
    ({'buffer_on_start': 'yes'}, 'buffer_on_start must be true or false'),
    ({'meta_model_path': 3}, 'meta_model_path must be a string'),
    ({'heldout_fraction': 1.0}, 'heldout_fraction must be in (0, 1)'),
    ({'progress_period': 1.5}, 'progress_period must be in (0, 1]'),
    ({'u_min': 2.0}, 'u_min <= u_max'),
    ({'excitation': 'chirp'}, 'excitation must be one of random_hold, multisine, prbs'),
    ({'excitation_amplitude': 0.0}, 'excitation_amplitude must be in (0, 1]'),
    ({'family': 'quadruple_tank', 'excitation_center': [3.0, 3.0],
      'excitation_amplitude': 0.8}, 'excitation_center [3.0, 3.0] +- excitation_amplitude x half'),
    ({'family': 'quadruple_tank', 'excitation_center': 3.0}, 'excitation_center needs one value '
                                                             'per input (2)'),
    ({'state_bound': 0.5}, 'initial states of family vanderpol reach beyond state_bound 0.5'),
    ({'family': 'quadruple_tank', 'u_max': [12.0, 10.0]}, 'outside those of family'),
    ({'online_noise_std': -0.1}, 'online_noise_std must be >= 0'),
    ({'online_r': 0.0}, 'online_r must be > 0'),
    ({'oracle_batch': 0}, 'oracle_batch must be >= 1'),
    ({'adapt_lr': 0.0}, 'adapt_lr must be > 0'),
    ({'episode_samples': 30}, 'episode_samples: its D_tr / D_test parts'),
    ({'target_buffer_size': 95}, 'target_buffer_size: its training / held-out parts'),
    ({'seed': -1}, 'seed must be >= 0'),
])
def test_bad_values_name_the_parameter(overrides, match):
    with pytest.raises(ParameterError, match=re.escape(match)):
        parse_params(_raw(**overrides))


@pytest.mark.parametrize('size', [95, 96, 99, 100, 101, 110, 124, 125])
def test_the_buffer_size_check_agrees_with_the_split(size):
    # H + T = 20 by default: accepted exactly when a full buffer of consecutive samples gives
    # at least one window in its training part and one in its held-out part.
    steps = np.arange(1, size + 1)
    full = TargetSamples(steps, np.zeros((size, 1)), np.zeros((size, 2)))
    train, held, _ = split_target(full, 0, 0.2, 10.0)
    fits = all(windows(part, 20)[0].shape[0] > 0 for part in (train, held))
    try:
        parse_params(_raw(target_buffer_size=size))
        accepted = True
    except ParameterError:
        accepted = False
    assert accepted == fits


def test_meta_request_zero_means_the_parameter():
    base = replace(MetaConfig(), iterations=50, seed=3)
    assert resolve_meta_request(MetaTrain.Request(), base, False) == (base, False)
    assert resolve_meta_request(MetaTrain.Request(), base, True) == (base, True)
    config, online = resolve_meta_request(MetaTrain.Request(
        method='maml', iterations=5, batch_size=3, inner_steps=2, gamma=0.5, lr_inner=0.1,
        lr_outer=0.01, cg_steps=4, seed=9, online_collection=True), base, False)
    assert config == replace(base, method='maml', iterations=5, batch_size=3, inner_steps=2,
                             gamma=0.5, lr_inner=0.1, lr_outer=0.01, cg_steps=4, seed=9)
    assert online
    assert resolve_meta_request(MetaTrain.Request(gamma=-1.0), base, False)[0].gamma == 1.0


def test_meta_request_anchor_weight_zero_is_no_anchor_and_negative_the_parameter():
    """w = 0 is a real value (eq. (outer) as written), so 'the parameter' is a negative w, the
    request's default."""
    base = replace(MetaConfig(), init_loss_weight=0.1)
    assert MetaTrain.Request().init_loss_weight < 0
    assert resolve_meta_request(MetaTrain.Request(), base, False)[0].init_loss_weight == 0.1
    for w in (0.0, 0.3):
        config, _ = resolve_meta_request(MetaTrain.Request(init_loss_weight=w), base, False)
        assert config.init_loss_weight == w


@pytest.mark.parametrize('fields,match', [
    ({'method': 'supervised'}, "no meta-training phase: call adapt with method 'supervised'"),
    ({'method': 'reptile'}, "unknown method 'reptile'"),
    ({'lr_inner': -0.1}, 'lr_inner must be >= 0'),
    ({'lr_outer': NAN}, 'lr_outer must be finite'),
    ({'gamma': NAN}, 'gamma must be finite'),
    ({'init_loss_weight': NAN}, 'init_loss_weight must be finite'),
])
def test_bad_meta_requests(fields, match):
    with pytest.raises(ValueError, match=match):
        resolve_meta_request(MetaTrain.Request(**fields), MetaConfig(), False)


def test_adapt_request_zero_means_the_parameter():
    adapt, oracle = AdaptConfig(steps=20, lr=0.05, gamma=0.5), OracleConfig(steps=500, lr=3e-3)
    assert resolve_adapt_request(Adapt.Request(), adapt, oracle) == AdaptJob('', 20, 0.05, 0.0,
                                                                             0)
    assert resolve_adapt_request(Adapt.Request(gamma=-1.0), adapt, oracle).gamma == 0.5
    assert resolve_adapt_request(Adapt.Request(method='maml', steps=3, lr=0.1, gamma=2.0,
                                               n_samples=100), adapt, oracle) == AdaptJob(
        'maml', 3, 0.1, 2.0, 100)
    assert resolve_adapt_request(Adapt.Request(method='oracle'), adapt, oracle) == AdaptJob(
        'oracle', 500, 3e-3, 0.0, 0)


def test_a_request_names_its_model_class_or_takes_the_nodes():
    nssm = parse_params({name: spec.default for name, spec in PARAMETERS.items()})
    narx = replace(nssm, model_class='feature_narx')
    for request in (MetaTrain.Request, Adapt.Request):
        assert request_class(request(), nssm) == 'nssm'
        assert request_class(request(), narx) == 'feature_narx'
        assert request_class(request(model_class='feature_narx'), nssm) == 'feature_narx'
        assert request_class(request(model_class='nssm'), narx) == 'nssm'
        with pytest.raises(ValueError, match="unknown model_class 'narx'; expected one of '', "
                                             "'nssm', 'feature_narx'"):
            request_class(request(model_class='narx'), nssm)
    job = resolve_adapt_request(Adapt.Request(method='arx'), AdaptConfig(), OracleConfig(),
                                'feature_narx')
    assert (job.method, job.model_class) == ('arx', 'feature_narx')


@pytest.mark.parametrize('fields,match', [
    ({'method': 'reptile'}, "unknown method 'reptile'"),
    ({'lr': -0.1}, 'lr must be finite and >= 0'),
    ({'lr': INF}, 'lr must be finite and >= 0'),
    ({'gamma': NAN}, 'gamma must be finite'),
])
def test_bad_adapt_requests(fields, match):
    with pytest.raises(ValueError, match=match):
        resolve_adapt_request(Adapt.Request(**fields), AdaptConfig(), OracleConfig())


def test_the_request_defaults_and_only_they_are_live():
    """Live: the parameter behind each request field that falls back to one (docs/learner.md);
    a change reaches the next request, resolved against the re-parsed config."""
    # request_id names a call (docs/nodes.md, calls that are safe to repeat): no default;
    # model_class falls back to the node's class, read-only.
    meta_fields = set(MetaTrain.Request.get_fields_and_field_types()) - {'request_id',
                                                                         'model_class'}
    adapt_fields = set(Adapt.Request.get_fields_and_field_types()) - {
        'method', 'n_samples', 'request_id', 'model_class'}
    expected = meta_fields | {f'adapt_{f}' for f in adapt_fields} | {
        f'oracle_{f}' for f in adapt_fields - {'gamma'}}
    assert {name for name, spec in PARAMETERS.items() if spec.live} == expected
    changed = parse_params(_raw(iterations=7, adapt_lr=0.01))
    config, _ = resolve_meta_request(MetaTrain.Request(), changed.meta, False)
    job = resolve_adapt_request(Adapt.Request(), changed.adapt, changed.oracle)
    assert (config.iterations, job.lr) == (7, 0.01)
