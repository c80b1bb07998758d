"""A learned model <-> the model fields of an NssmWeights message, as plain arrays (no rclpy,
no message, no torch: torch code takes the arrays with ``nssm.torch_params``).

Two classes (:data:`MODEL_CLASSES`, the message's ``model_class``): the NSSM of eq. (SSM) and
the feature NARX. Written by :func:`fields_from_weights` (NSSM) or :func:`fields_from_narx`;
read by :func:`model_from_fields` (either: :class:`DecodedWeights` or :class:`DecodedNarx`) or
:func:`weights_from_fields` (an NSSM only); :class:`WeightsError` names what is wrong. A feature
NARX's sizes travel where they mean the same (``n_z``: n_s, ``history``: its order,
``encoder_layers``: g's widths) and in ``features``. Fields added since the first recordings
(:data:`ADDED_FIELDS`) read as their defaults where a message has none (an NSSM). The run
information (version, method, stage, losses, seed) is the caller's.
"""
from array import array
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Tuple, Union

import numpy as np

from metampc_model.arrays import as_numpy
from metampc_model.narx_shape import NarxShape
from metampc_model.normalisation import Normalisation
from metampc_model.nssm_config import NssmConfig, param_shapes

# The model classes a message may carry: the paper's NSSM and the feature NARX.
MODEL_CLASSES = ('nssm', 'feature_narx')
MODEL_FIELDS = ('model_class', 'n_z', 'n_u', 'n_y', 'history', 'encoder_layers', 'features',
                'names', 'shape_offsets', 'shapes', 'params', 'u_mean', 'u_std', 'y_mean',
                'y_std')
# Fields added to the message since the first recordings, with the value a message without
# them means: an NSSM ('' is 'nssm'), no features.
ADDED_FIELDS = {'model_class': '', 'features': 0}


@dataclass
class FlatWeights:
    """Parameters as the NssmWeights message carries them.

    ``shapes[shape_offsets[i]:shape_offsets[i+1]]`` is the shape of ``names[i]``
    (len(shape_offsets) = len(names) + 1); ``params`` concatenates the row-major flattened
    parameters in the order of ``names``, float32.
    """

    names: List[str]
    shape_offsets: List[int]
    shapes: List[int]
    params: np.ndarray = field(repr=False)

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> 'FlatWeights':
        """From a parameter dict (torch tensors or arrays, any float dtype), in its order."""
        names = list(params)
        offsets, shapes = [0], []
        for name in names:
            shapes.extend(int(s) for s in params[name].shape)
            offsets.append(len(shapes))
        flat = np.concatenate([as_numpy(params[n], np.float32).reshape(-1)
                               for n in names]) if names else np.zeros(0, np.float32)
        return cls(names, offsets, shapes, flat)

    def shape_of(self, i: int) -> Tuple[int, ...]:
        return tuple(self.shapes[self.shape_offsets[i]:self.shape_offsets[i + 1]])

    def to_params(self, config: Union[NssmConfig, NarxShape]) -> Dict[str, np.ndarray]:
        """Rebuild the parameter dict (float32 arrays, canonical order); ValueError if it does
        not fit the architecture (an NSSM's config or a feature NARX's shape)."""
        expected = _shapes(config)
        if len(self.shape_offsets) != len(self.names) + 1:
            raise ValueError('shape_offsets must have one entry more than names')
        got = {n: self.shape_of(i) for i, n in enumerate(self.names)}
        if got != dict(expected):
            raise ValueError(f'weights do not fit the model {config}: got {got}')
        sizes = [int(np.prod(got[n])) for n in self.names]
        flat = np.asarray(self.params, dtype=np.float32).reshape(-1)
        if flat.size != sum(sizes):
            raise ValueError(f'{flat.size} parameters, shapes need {sum(sizes)}')
        if not np.all(np.isfinite(flat)):
            raise ValueError('weights have non-finite entries')
        chunks = dict(zip(self.names, np.split(flat, np.cumsum(sizes)[:-1])))
        return {n: chunks[n].reshape(s).copy() for n, s in expected.items()}


def _shapes(config: Union[NssmConfig, NarxShape]) -> Mapping[str, Tuple[int, ...]]:
    """The parameter shapes of an NSSM's config or a feature NARX's shape, canonical order."""
    return config.param_shapes() if isinstance(config, NarxShape) else param_shapes(config)


class WeightsError(ValueError):
    """The model fields do not describe a usable NSSM; the message is one short reason."""


@dataclass
class DecodedWeights:
    """An NSSM rebuilt from model fields: architecture, normalisation, parameters (float32
    numpy arrays, canonical order; torch code converts them with ``nssm.torch_params``)."""

    config: NssmConfig
    norm: Normalisation
    params: Dict[str, np.ndarray]
    model_class = 'nssm'


@dataclass
class DecodedNarx:
    """A feature NARX rebuilt from model fields: shape, normalisation, parameters (float32
    numpy arrays, canonical order; ``metampc_model.narx_predictor.NarxPredictor`` takes them)."""

    shape: NarxShape
    norm: Normalisation
    params: Dict[str, np.ndarray]
    model_class = 'feature_narx'


def _flat_fields(expected: Mapping[str, Tuple[int, ...]], params: Mapping[str, Any]
                 ) -> Dict[str, Any]:
    """The parameter fields (names, shape_offsets, shapes, params) of `params` in the order of
    `expected`."""
    flat = FlatWeights.from_params({name: params[name] for name in expected})
    values = array('f')
    values.frombytes(np.ascontiguousarray(flat.params, dtype=np.float32).tobytes())
    return {'names': list(flat.names), 'shape_offsets': array('I', flat.shape_offsets),
            'shapes': array('I', flat.shapes), 'params': values}


def fields_from_weights(config: NssmConfig, norm: Normalisation,
                        params: Mapping[str, Any]) -> Dict[str, Any]:
    """The model fields of an NssmWeights message for this NSSM (parameters: torch tensors or
    arrays).

    Returns a dict keyed by :data:`MODEL_FIELDS`: ``model_class`` 'nssm', dimensions as int,
    ``encoder_layers``, ``shape_offsets`` and ``shapes`` as ``array('I')``, ``names`` as a
    list of str, ``params`` as ``array('f')`` (float32, canonical order of
    :func:`param_shapes`), the normalisation as ``array('d')``. Raises WeightsError if the
    parameters do not fit ``config``.
    """
    expected = param_shapes(config)
    got = {name: tuple(params[name].shape) for name in expected if name in params}
    if got != dict(expected):
        raise WeightsError(f'parameters do not fit {config}')
    return {'model_class': 'nssm', 'n_z': int(config.n_z), 'n_u': int(config.n_u),
            'n_y': int(config.n_y), 'history': int(config.history),
            'encoder_layers': array('I', config.hidden), 'features': 0,
            **_flat_fields(expected, params),
            **{name: array('d', value) for name, value in norm.to_dict().items()}}


def fields_from_narx(shape: NarxShape, norm: Normalisation, params: Mapping[str, Any]
                     ) -> Dict[str, Any]:
    """The model fields of an NssmWeights message for this feature NARX (parameters: torch
    tensors or arrays), typed as :func:`fields_from_weights` types them: ``model_class``
    'feature_narx', ``n_z`` its state's size n_s, ``history`` its order p,
    ``encoder_layers`` g's hidden widths, ``features`` F. Raises WeightsError if the
    parameters do not fit ``shape``."""
    expected = shape.param_shapes()
    got = {name: tuple(params[name].shape) for name in expected if name in params}
    if got != dict(expected):
        raise WeightsError(f'parameters do not fit {shape}')
    return {'model_class': 'feature_narx', 'n_z': int(shape.n_s), 'n_u': int(shape.n_u),
            'n_y': int(shape.n_y), 'history': int(shape.order),
            'encoder_layers': array('I', shape.hidden), 'features': int(shape.features),
            **_flat_fields(expected, params),
            **{name: array('d', value) for name, value in norm.to_dict().items()}}


def fields_of(msg: Any) -> Dict[str, Any]:
    """The :data:`MODEL_FIELDS` of any object that has them as attributes (e.g. a message; a
    recorded one from before an :data:`ADDED_FIELDS` field reads its default)."""
    return {name: getattr(msg, name) if name not in ADDED_FIELDS
            else getattr(msg, name, ADDED_FIELDS[name]) for name in MODEL_FIELDS}


def model_class_of(fields: Mapping[str, Any]) -> str:
    """The model class the fields describe ('nssm' where they name none: older messages).

    Raises:
        WeightsError: a class that is not one of :data:`MODEL_CLASSES`.
    """
    name = str(fields.get('model_class', ADDED_FIELDS['model_class'])) or 'nssm'
    if name not in MODEL_CLASSES:
        raise WeightsError(f'unknown model class {name!r} (known: {", ".join(MODEL_CLASSES)})')
    return name


def model_from_fields(fields: Mapping[str, Any]) -> Union[DecodedWeights, DecodedNarx]:
    """Rebuild and check the model the fields describe, of either class
    (:func:`model_class_of`): :class:`DecodedWeights` (:func:`weights_from_fields`'s checks)
    or :class:`DecodedNarx` (the same checks on its shape).

    Raises:
        WeightsError: the first problem found, in one line.
    """
    missing = [name for name in MODEL_FIELDS if name not in fields and name not in ADDED_FIELDS]
    if missing:
        raise WeightsError(f'missing fields {missing}')
    narx = model_class_of(fields) == 'feature_narx'
    try:
        if narx:
            config = NarxShape(n_u=int(fields['n_u']), n_y=int(fields['n_y']),
                               order=int(fields['history']),
                               features=int(fields.get('features', 0)),
                               hidden=tuple(int(w) for w in fields['encoder_layers']))
            if int(fields['n_z']) != config.n_s:
                raise ValueError(f'n_z = {int(fields["n_z"])} is not the state size '
                                 f'n_s = {config.n_s} of the feature NARX {config}')
        else:
            config = NssmConfig(n_u=int(fields['n_u']), n_y=int(fields['n_y']),
                                n_z=int(fields['n_z']), history=int(fields['history']),
                                hidden=tuple(int(w) for w in fields['encoder_layers']))
            config.validate()
        norm = Normalisation(**{name: np.asarray(fields[name], dtype=np.float64)
                                for name in ('u_mean', 'u_std', 'y_mean', 'y_std')})
        norm.validate(config)     # its n_u, n_y
    except (TypeError, ValueError) as err:
        raise WeightsError(str(err)) from None
    names = [str(n) for n in fields['names']]
    offsets = [int(o) for o in fields['shape_offsets']]
    shapes = [int(s) for s in fields['shapes']]
    if (len(offsets) != len(names) + 1 or offsets[0] != 0 or offsets[-1] != len(shapes)
            or any(b < a for a, b in zip(offsets, offsets[1:]))):
        raise WeightsError(f'shape_offsets {offsets} do not index {len(shapes)} shape entries '
                           f'for {len(names)} names')
    flat = FlatWeights(names, offsets, shapes, np.asarray(fields['params'], dtype=np.float32))
    expected = _shapes(config)
    got = {name: flat.shape_of(i) for i, name in enumerate(names)}
    for name, shape in expected.items():
        if got.get(name) != shape:
            raise WeightsError(f'{name} has shape {got.get(name)}, the architecture needs '
                               f'{shape}')
    if len(names) != len(expected):
        raise WeightsError(f'unexpected parameters {sorted(set(names) - set(expected))}')
    try:
        params = flat.to_params(config)
    except ValueError as err:  # parameter count, non-finite values
        raise WeightsError(str(err)) from None
    return (DecodedNarx if narx else DecodedWeights)(config, norm, params)


def weights_from_fields(fields: Mapping[str, Any]) -> DecodedWeights:
    """Rebuild and check an NSSM from model fields (sequences of any kind: array, list, numpy),
    for readers that take an NSSM only (a feature NARX is refused: :func:`model_from_fields`
    reads both).

    Checks: positive dimensions and widths, parameter names and shapes exactly those of the
    architecture (in any order), the parameter count, finite parameters, normalisation of the
    right sizes, finite, scales > 0.

    Raises:
        WeightsError: the first problem found, in one line.
    """
    if model_class_of(fields) != 'nssm':
        raise WeightsError(f'a {model_class_of(fields)} model, not an NSSM')
    return model_from_fields(fields)
