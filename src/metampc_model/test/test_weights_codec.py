"""NSSM <-> NssmWeights fields (weights_codec) and the hand-built model (manual_model)."""
from array import array
import math

from metampc_msgs.msg import NssmWeights
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from metampc_model.manual_model import linearised_vdp, linearised_vdp_nssm
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import init_params
from metampc_model.nssm_config import NssmConfig
from metampc_model.predictor import NssmPredictor
from metampc_model.weights_codec import (fields_from_weights, fields_of, MODEL_FIELDS,
                                         weights_from_fields, WeightsError)
from metampc_plant.integrate import rk4_sample
from metampc_plant.registry import get_family
from metampc_plant.simulator import Plant, PlantConfig

CONFIG = NssmConfig(n_z=5, history=10, hidden=(128, 128))
NORM = Normalisation([0.1], [0.5], [0.2, -0.1], [1.5, 2.0])


def test_message_round_trip_is_exact():
    params = init_params(CONFIG, seed=4)
    msg = NssmWeights(version=3, method='imaml', stage='adapted',
                      **fields_from_weights(CONFIG, NORM, params))
    wire = deserialize_message(serialize_message(msg), NssmWeights)   # through CDR
    decoded = weights_from_fields(fields_of(wire))
    assert decoded.config == CONFIG and decoded.norm.to_dict() == NORM.to_dict()
    assert list(decoded.params) == list(params)
    for name, value in params.items():
        assert decoded.params[name].dtype == np.float32
        assert np.array_equal(decoded.params[name], value.numpy()), name
    assert len(wire.params) == sum(v.numel() for v in params.values()) == 21_165


def test_parameters_may_come_in_any_order():
    params = init_params(CONFIG, seed=1)
    shuffled = {name: params[name] for name in reversed(list(params))}
    fields = fields_from_weights(CONFIG, NORM, params)
    names, offsets, shapes, flat = [], [0], [], []
    for name, value in shuffled.items():
        names.append(name)
        shapes.extend(value.shape)
        offsets.append(len(shapes))
        flat.append(value.reshape(-1).numpy())
    fields.update(names=names, shape_offsets=offsets, shapes=shapes,
                  params=np.concatenate(flat))
    decoded = weights_from_fields(fields)
    assert all(np.array_equal(decoded.params[n], params[n].numpy()) for n in params)


def _fields(**changes):
    fields = fields_from_weights(CONFIG, NORM, init_params(CONFIG, seed=0))
    fields = {name: (value.tolist() if isinstance(value, array) else value)
              for name, value in fields.items()}
    fields.update(changes)
    return fields


def _with(name, index, value):
    values = _fields()[name]
    values[index] = value
    return {name: values}


BAD = {
    'nan': (_with('params', 11, math.nan), 'non-finite'),
    'inf': (_with('params', -1, math.inf), 'non-finite'),
    'shape': (_with('shapes', 0, 129), 'encoder.0.weight has shape (129, 30)'),
    'count': ({'params': _fields()['params'][:-1]}, '21164 parameters, shapes need 21165'),
    'offsets': (_with('shape_offsets', 1, 99), 'shape_offsets'),
    'extra name': ({'names': _fields()['names'] + ['D'],
                    'shape_offsets': _fields()['shape_offsets'] + [len(_fields()['shapes']) + 1],
                    'shapes': _fields()['shapes'] + [1]}, "unexpected parameters ['D']"),
    'missing name': ({'names': _fields()['names'][:-1],
                      'shape_offsets': _fields()['shape_offsets'][:-1],
                      'shapes': _fields()['shapes'][:-2]}, 'C has shape None'),
    'n_z': ({'n_z': 0}, 'n_z must be >= 1'),
    'std': (_with('y_std', 1, 0.0), 'scales must be > 0'),
    'mean size': ({'u_mean': [0.0, 0.0]}, 'u_mean must be 1 finite numbers'),
    'mean nan': (_with('y_mean', 0, math.nan), 'y_mean must be 2 finite numbers'),
}


@pytest.mark.parametrize('case', sorted(BAD))
def test_bad_fields_are_rejected_with_one_reason(case):
    changes, reason = BAD[case]
    with pytest.raises(WeightsError) as err:
        weights_from_fields(_fields(**changes))
    assert reason in str(err.value) and '\n' not in str(err.value)


def test_missing_fields_and_unfitting_parameters():
    fields = _fields()
    del fields['shapes']
    with pytest.raises(WeightsError, match=r"missing fields \['shapes'\]"):
        weights_from_fields(fields)
    assert set(MODEL_FIELDS) <= set(NssmWeights.get_fields_and_field_types())
    with pytest.raises(WeightsError, match='parameters do not fit'):
        fields_from_weights(NssmConfig(n_z=4), NORM, init_params(CONFIG, seed=0))


@pytest.mark.parametrize('theta', [-0.7, 0.0, 1.3])
def test_linearisation_is_the_plants_jacobian_at_the_origin(theta):
    """Central differences of the plant's own RK4 sample at x = 0, u = 0."""
    a, b = linearised_vdp(theta, 0.1)
    eps = 1e-6
    cols = []
    for dx in (np.array([eps, 0.0, 0.0]), np.array([0.0, eps, 0.0]), np.array([0.0, 0.0, eps])):
        vdp, th = get_family('vanderpol'), np.array([[theta]])
        plus = rk4_sample(vdp, dx[None, :2], dx[None, 2:], th, 0.1, 10)[0]
        minus = rk4_sample(vdp, -dx[None, :2], -dx[None, 2:], th, 0.1, 10)[0]
        cols.append((plus - minus) / (2 * eps))
    np.testing.assert_allclose(np.column_stack(cols), np.hstack([a, b]), atol=1e-8)


@pytest.mark.parametrize('model', [{}, {'n_z': 4, 'hidden': (8, 8), 'history': 5},
                                   {'hidden': ()}])
def test_manual_model_encodes_the_last_output_and_predicts_the_linear_plant(model):
    """theta = 0: the plant is linear and the ZOH model exact (RK4 error ~1e-9 at dt = 0.1),
    so the predictions match the plant up to the float32 rounding of the parameters."""
    config, norm, params = linearised_vdp_nssm(0.0, 0.1, **model)
    predictor = NssmPredictor(config, norm, params)
    rng = np.random.default_rng(0)
    h = config.history
    u_hist, y_hist = rng.uniform(-1, 1, (h, 1)), rng.uniform(-2, 2, (h, 2))
    z = predictor.encode(u_hist, y_hist)
    np.testing.assert_allclose(z, np.r_[y_hist[-1], np.zeros(config.n_z - 2)], atol=1e-6)
    plant = Plant(PlantConfig(theta=(0.0,), x0=tuple(y_hist[-1])))
    u_future = rng.uniform(-1, 1, (15, 1))
    actual = np.array([plant.step(u) for u in u_future])
    np.testing.assert_allclose(predictor.predict(u_hist, y_hist, u_future), actual, atol=1e-5)


def test_manual_model_discretisation_is_exact_for_a_held_input():
    """The augmented matrix exponential against the closed form of the undamped oscillator."""
    a, b = linearised_vdp(0.0, 0.3)
    c, s = math.cos(0.3), math.sin(0.3)
    np.testing.assert_allclose(a, [[c, s], [-s, c]], atol=1e-14)
    np.testing.assert_allclose(b[:, 0], [1 - c, s], atol=1e-14)


def _narx():
    import torch
    from metampc_model.feature_narx import FeatureNarx, init_params as narx_params, NarxShape
    shape = NarxShape(1, 2, order=3, features=5, hidden=(7, 4))
    params = narx_params(shape, 3)
    params['head'] = torch.randn(params['head'].shape, generator=torch.Generator().manual_seed(
        1), dtype=torch.float64)
    return FeatureNarx(shape, NORM, params)


def test_a_feature_narx_round_trips_through_the_message_and_predicts_as_the_torch_model():
    import torch
    from metampc_model.feature_narx import regressors
    from metampc_model.narx_predictor import NarxPredictor
    from metampc_model.weights_codec import (DecodedNarx, fields_from_narx, model_from_fields)
    model = _narx()
    msg = NssmWeights(version=2, method='imaml', stage='adapted',
                      **fields_from_narx(model.shape, NORM, model.params))
    wire = deserialize_message(serialize_message(msg), NssmWeights)
    assert (wire.model_class, wire.n_z, wire.history, list(wire.encoder_layers),
            wire.features) == ('feature_narx', model.shape.n_s, 3, [7, 4], 5)
    decoded = model_from_fields(fields_of(wire))
    assert isinstance(decoded, DecodedNarx) and decoded.shape == model.shape
    assert list(decoded.params) == list(model.shape.param_shapes())
    for name, value in model.params.items():
        assert np.array_equal(decoded.params[name], value.float().numpy()), name
    with pytest.raises(WeightsError, match='a feature_narx model, not an NSSM'):
        weights_from_fields(fields_of(wire))
    with pytest.raises(WeightsError, match='n_z = 4 is not the state size n_s = 8'):
        model_from_fields({**fields_of(wire), 'n_z': 4})
    with pytest.raises(WeightsError, match="unknown model class 'gp'"):
        model_from_fields({**fields_of(wire), 'model_class': 'gp'})
    # the controller's numpy evaluation against the torch model's regressors (float32 weights)
    f32 = {k: torch.from_numpy(v.astype(np.float64)) for k, v in decoded.params.items()}
    predictor = NarxPredictor(decoded.shape, NORM, decoded.params)
    rng = np.random.default_rng(0)
    s, u = rng.normal(size=model.shape.n_s), rng.normal(size=1)
    mean, std = predictor._mean, predictor._std
    phi = regressors(model.shape, f32, torch.from_numpy((s - mean) / std),
                     torch.from_numpy((u - NORM.u_mean) / NORM.u_std))
    expected = (f32['head'] @ phi).numpy() * NORM.y_std + NORM.y_mean
    np.testing.assert_allclose(predictor.step(s, u), expected, rtol=1e-12)


def test_weights_of_a_recording_from_before_the_model_class_field_decode_as_an_nssm():
    """A recording carries its own definition of the message: one from before model_class
    and features decodes (rosbags, from that definition) to a message without them."""
    import os
    from ament_index_python.packages import get_package_share_directory
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores
    jazzy, store = get_typestore(Stores.ROS2_JAZZY), get_typestore(Stores.EMPTY)
    store.register({n: jazzy.fielddefs[n] for n in ('builtin_interfaces/msg/Time',
                                                    'std_msgs/msg/Header')})
    with open(os.path.join(get_package_share_directory('metampc_msgs'), 'msg',
                           'NssmWeights.msg')) as f:
        now = f.read()
    old = '\n'.join(line for line in now.splitlines()
                    if not line.startswith(('string model_class', 'uint32 features')))
    store.register(get_types_from_msg(old, 'metampc_msgs/msg/NssmWeights'))
    t = store.types
    fields = fields_from_weights(CONFIG, NORM, init_params(CONFIG, seed=4))
    del fields['model_class'], fields['features']
    kind = 'metampc_msgs/msg/NssmWeights'
    values = {name: (np.asarray(v) if isinstance(v, array) else v) for name, v in fields.items()}
    values.update(header=t['std_msgs/msg/Header'](stamp=t['builtin_interfaces/msg/Time'](
        sec=0, nanosec=0), frame_id=''), version=1, method='imaml', stage='meta', train_loss=0.0,
        train_steps=0, train_samples=0, seed=0, train_time=0.0, request_step=0)
    recorded = store.deserialize_cdr(store.serialize_cdr(t[kind](**values), kind), kind)
    assert not hasattr(recorded, 'model_class')
    decoded = weights_from_fields(fields_of(recorded))
    assert decoded.config == CONFIG and decoded.model_class == 'nssm'
