"""The named protocols turn the experiment's requests into the tuned or the paper's set-up."""
import re

import pytest

from metampc_bringup.experiment_config import ConfigError, from_mapping
from metampc_common import renames

REQUESTS = {'meta_train': {'imaml': {'gamma': 3.0, 'inner_steps': 10}, 'maml': {'lr_inner': 0.02}},
            'adapt': {'imaml': {'steps': 20, 'lr': 0.2}, 'maml': {'lr': 0.3},
                      'supervised': {'lr': 0.3}, 'oracle': {}}}


def test_tuned_sends_the_requests_as_written():
    config = from_mapping(REQUESTS).validate()
    assert config.protocol == 'tuned'
    assert config.meta_request('imaml') == {'gamma': 3.0, 'inner_steps': 10}
    assert config.adapt_request('imaml') == {'steps': 20, 'lr': 0.2}
    assert config.meta_request('maml_unrolled') == {}


def test_paper_settings_collects_online_and_adapts_imaml_by_eq_infer():
    config = from_mapping({**REQUESTS, 'protocol': 'paper_settings'}).validate()
    assert config.meta_request('imaml') == {'gamma': 3.0, 'inner_steps': 10,
                                            'online_collection': True}
    assert config.meta_request('maml') == {'lr_inner': 0.02, 'online_collection': True}
    assert config.adapt_request('imaml') == {'steps': 20, 'lr': 0.2, 'gamma': 3.0}
    assert config.adapt_request('maml') == {'lr': 0.3, 'gamma': 0.0}
    assert config.adapt_request('supervised') == {'lr': 0.3, 'gamma': 0.0}
    assert config.adapt_request('oracle') == {}
    # the requests as configured are left as they are
    assert config.meta_train['imaml'] == {'gamma': 3.0, 'inner_steps': 10}


def test_bad_protocol_and_paper_settings_without_imaml_gamma_are_refused():
    with pytest.raises(ConfigError,
                       match="protocol must be one of tuned, paper_settings, got 'papr'"):
        from_mapping({'protocol': 'papr'}).validate()
    with pytest.raises(ConfigError, match='set meta_train.imaml.gamma'):
        from_mapping({'protocol': 'paper_settings'}).validate()
    from_mapping({'protocol': 'paper_settings', 'methods': ['maml', 'nmpc']}).validate()


@pytest.fixture
def fresh_warnings(monkeypatch):
    """Warnings not yet written in this process (each is written once per process)."""
    monkeypatch.setattr(renames, '_written', set())


def _warnings(capsys) -> list:
    return [line for line in capsys.readouterr().err.splitlines() if line]


OLD = {  # renamed in this release: (old mapping, new mapping, the warning line)
    'protocol': ({'protocol': 'paper'}, {'protocol': 'paper_settings'},
                 "warning: config: protocol: 'paper' is renamed 'paper_settings'; the old value "
                 'will be removed in the next release'),
    'scenario': ({'scenario': 'paper'}, {'scenario': 'adapt_once'},
                 "warning: config: scenario: 'paper' is renamed 'adapt_once'; the old value will "
                 'be removed in the next release'),
    'loss horizon': ({'learner': {'horizon': 7}}, {'learner': {'loss_horizon': 7}},
                     'warning: config: learner.horizon is renamed loss_horizon; the old name '
                     'will be removed in the next release'),
    'reference': ({'controller': {'reference': 'paper'}},
                  {'controller': {'reference': 'setpoint_sequence'}},
                  "warning: config: controller.reference: 'paper' is renamed "
                  "'setpoint_sequence'; the old value will be removed in the next release"),
}


@pytest.mark.parametrize('case', sorted(OLD))
def test_an_old_name_works_with_one_warning_naming_the_new(case, fresh_warnings, capsys):
    old, new, line = OLD[case]
    meta = {'meta_train': {'imaml': {'gamma': 1.0}}}
    got = [from_mapping({**meta, **old}).validate() for _ in range(2)]
    assert _warnings(capsys) == [line]      # once, though loaded twice
    assert got[0] == got[1] == from_mapping({**meta, **new}).validate()
    assert _warnings(capsys) == []


def test_the_old_and_the_new_name_together_are_refused(fresh_warnings):
    with pytest.raises(ConfigError, match='^config: learner.horizon and loss_horizon are both '
                                          'given: horizon is renamed loss_horizon; give '
                                          'loss_horizon only$'):
        from_mapping({'learner': {'horizon': 7, 'loss_horizon': 7}})


def test_request_fields_take_the_requests_types():
    """A YAML integer where a request wants a double is that double (the generated message
    code aborted the process on it: a pendulum run stopped so); a field that cannot be the
    request's type is one ConfigError naming it."""
    from metampc_msgs.srv import Adapt, MetaTrain
    config = from_mapping({'meta_train': {'imaml': {'lr_outer': 1, 'batch_size': 4.0}},
                           'adapt': {'imaml': {'lr': 1, 'steps': 3}}}).validate()
    meta, adapt = config.meta_request('imaml'), config.adapt_request('imaml')
    assert meta == {'lr_outer': 1.0, 'batch_size': 4} and type(meta['lr_outer']) is float
    assert MetaTrain.Request(method='imaml', **meta).lr_outer == 1.0
    assert Adapt.Request(method='imaml', **adapt).lr == 1.0
    for bad, match in (({'iterations': 4.5}, 'meta_train.imaml.iterations: 4.5 is not a uint32'),
                       ({'lr_outer': 'fast'}, "meta_train.imaml.lr_outer: 'fast' is not a double"),
                       ({'online_collection': 1}, 'is not a boolean')):
        with pytest.raises(ConfigError, match=match):
            from_mapping({'meta_train': {'imaml': bad}}).validate()


def test_reference_inputs_give_each_seed_the_set_points_its_target_can_hold():
    """The quadruple tank's set-points from pump voltages: per seed, the levels of theta*'s
    steady state (closed form: each lower tank's outflow a_i sqrt(2 g h_i) equals its inflow
    g_i k_i v_i + (1 - g_j) k_j v_j), row after row, on the tracked outputs."""
    from metampc_plant.families.quadruple_tank import GRAVITY, OUTLET, PUMP, SENSOR
    rows = [[3.0, 3.0], [2.6, 3.4]]
    config = from_mapping({'family': 'quadruple_tank', 'reference_inputs': rows})
    config.validate()
    for seed in (0, 7):
        g1, g2 = config.target_theta(seed)
        want = []
        for v1, v2 in rows:
            q = (g1 * PUMP[0] * v1 + (1 - g2) * PUMP[1] * v2,
                 g2 * PUMP[1] * v2 + (1 - g1) * PUMP[0] * v1)
            want += [SENSOR * (q[i] / OUTLET[i]) ** 2 / (2 * GRAVITY) for i in (0, 1)]
        params = config.node_parameters('controller', seed)
        assert params['reference_values'] == pytest.approx(want, rel=1e-8)
        assert (params['reference'], params['reference_per_output'],
                params['reference_outputs']) == ('setpoint_sequence', True, [0, 1])
        ctrl = config.node_config('controller', seed)
        assert ctrl.reference_params['setpoints'] == [tuple(params['reference_values'][:2]),
                                                      tuple(params['reference_values'][2:])]


@pytest.mark.parametrize('changes, message', [
    ({'reference_inputs': [[3.0]]}, 'reference_inputs must be rows of 2 input values'),
    ({'reference_inputs': [[3.0, 3.0]], 'controller': {'reference_values': [6.0]}},
     'reference_inputs sets the reference: leave reference_values out'),
    ({'reference_inputs': [[10.0, 10.0]]}, 'reference_inputs (seed 0): quadruple_tank: no '
                                           'steady state inside the state box'),
    ({'reference_inputs': [[-1.0, 3.0]]}, 'is not 2 values inside'),
])
def test_bad_reference_inputs_are_one_config_error(changes, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        from_mapping({'family': 'quadruple_tank', **changes}).validate()


def test_the_default_config_compares_both_model_classes_in_one_learner():
    """config/default.yaml: the feature NARX's methods (narx_*) beside the paper's NSSM's on
    a learner of the NSSM's class, each request naming its class; the paper's method alone
    is the same file with --methods imaml,maml,supervised,oracle,arx,nmpc."""
    import os
    from metampc_bringup.experiment_config import (experiment_method, learner_method, load,
                                                   METHODS)
    path = os.path.join(os.path.dirname(__file__), '..', '..', '..', 'config', 'default.yaml')
    config = load(path)
    assert config.node_config('learner', 0).model_class == 'nssm'
    assert config.methods == ['narx_imaml', 'narx_maml', 'narx_oracle', 'narx_arx', 'imaml',
                              'maml', 'supervised', 'oracle', 'arx', 'nmpc']
    assert config.meta_methods() == ['narx_imaml', 'narx_maml', 'imaml', 'maml']
    assert [learner_method(m) for m in config.meta_methods()] == [
        ('imaml', 'feature_narx'), ('maml', 'feature_narx'), ('imaml', ''), ('maml', '')]
    assert learner_method('arx') == ('arx', '') and learner_method('narx_arx') == (
        'arx', 'feature_narx')
    # the name a recorded model gets back, on either learner class
    for method in METHODS:
        name, model_class = learner_method(method)
        assert experiment_method(name, model_class or 'nssm', 'nssm') == method
    assert experiment_method('imaml', 'feature_narx', 'feature_narx') == 'imaml'
    paper = load(path, {'methods': ['imaml', 'maml', 'supervised', 'oracle', 'arx', 'nmpc']})
    assert paper.meta_request('imaml')['iterations'] == 300
    # requests per experiment name; the class is the name's, never a request field
    assert load(path, {'meta_train': {'narx_imaml': {'iterations': 5}}}).meta_request(
        'narx_imaml') == {'iterations': 5}
    with pytest.raises(ConfigError, match='meta_train: unknown method .narx_supervised.'):
        load(path, {'meta_train': {'narx_supervised': {}}})
    with pytest.raises(ConfigError, match=r'adapt.narx_imaml: unknown field\(s\) model_class'):
        load(path, {'adapt': {'narx_imaml': {'model_class': 'nssm'}}})
    with pytest.raises(ConfigError, match='methods must be distinct names out of'):
        load(path, {'methods': ['narx_supervised', 'nmpc']})
    with pytest.raises(ConfigError, match="the NSSM's only: not for narx_imaml"):
        load(path, {'protocol': 'paper_settings'})


def test_a_feature_narx_learner_refuses_methods_not_of_its_class():
    """learner.model_class feature_narx: its methods by their own names; supervised and the
    narx_ names (the other class's prefix) are refused, as is the NSSM's gain check."""
    narx = {'learner': {'model_class': 'feature_narx'}}
    config = from_mapping({**narx, 'methods': ['imaml', 'maml', 'oracle', 'arx', 'nmpc']})
    assert config.validate().node_config('learner', 0).model_class == 'feature_narx'
    for methods, unfit in ((['imaml', 'supervised', 'nmpc'], 'supervised'),
                           (['narx_imaml', 'nmpc'], 'narx_imaml')):
        with pytest.raises(ConfigError, match=f'methods {unfit}: not of learner.model_class '
                                              'feature_narx'):
            from_mapping({**narx, 'methods': methods}).validate()
    with pytest.raises(ConfigError, match="gain_check: the NSSM's only"):
        from_mapping({'learner': {'model_class': 'feature_narx', 'gain_check': True},
                      'methods': ['imaml']}).validate()
