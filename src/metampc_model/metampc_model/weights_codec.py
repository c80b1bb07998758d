"""NSSM <-> the model fields of an NssmWeights message, as plain arrays (no rclpy, no message).

The learner publishes with :func:`fields_from_weights` (config, normalisation and parameters,
torch tensors or arrays -> the fields typed as the message wants them) and the controller
reads with :func:`weights_from_fields` (fields -> numpy config, normalisation and parameters;
:class:`WeightsError` names what is wrong); both agree on :data:`MODEL_FIELDS`, the fields of
``metampc_msgs/msg/NssmWeights`` that describe the model of eq. (SSM) (dimensions, encoder
widths, the flat float32 parameters of :class:`FlatWeights`, the normalisation). The run
information (version, method, stage, losses, seed) is the caller's. No torch: torch code takes
the arrays with ``metampc_model.nssm.torch_params``.
"""
from array import array
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Tuple

import numpy as np

from metampc_model.arrays import as_numpy
from metampc_model.normalisation import Normalisation
from metampc_model.nssm_config import NssmConfig, param_shapes

MODEL_FIELDS = ('n_z', 'n_u', 'n_y', 'history', 'encoder_layers', 'names', 'shape_offsets',
                'shapes', 'params', 'u_mean', 'u_std', 'y_mean', 'y_std')


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

    def to_params(self, config: NssmConfig) -> Dict[str, np.ndarray]:
        """Rebuild the parameter dict (float32 arrays, canonical order); ValueError if it does
        not fit the architecture."""
        expected = param_shapes(config)
        if len(self.shape_offsets) != len(self.names) + 1:
            raise ValueError('shape_offsets must have one entry more than names')
        got = {n: self.shape_of(i) for i, n in enumerate(self.names)}
        if got != dict(expected):
            raise ValueError(f'weights do not fit the NSSM {config}: got {got}')
        sizes = [int(np.prod(got[n])) for n in self.names]
        flat = np.asarray(self.params, dtype=np.float32).reshape(-1)
        if flat.size != sum(sizes):
            raise ValueError(f'{flat.size} parameters, shapes need {sum(sizes)}')
        if not np.all(np.isfinite(flat)):
            raise ValueError('weights have non-finite entries')
        chunks = dict(zip(self.names, np.split(flat, np.cumsum(sizes)[:-1])))
        return {n: chunks[n].reshape(s).copy() for n, s in expected.items()}


class WeightsError(ValueError):
    """The model fields do not describe a usable NSSM; the message is one short reason."""


@dataclass
class DecodedWeights:
    """An NSSM rebuilt from model fields: architecture, normalisation, parameters (float32
    numpy arrays, canonical order; torch code converts them with ``nssm.torch_params``)."""

    config: NssmConfig
    norm: Normalisation
    params: Dict[str, np.ndarray]


def fields_from_weights(config: NssmConfig, norm: Normalisation,
                        params: Mapping[str, Any]) -> Dict[str, Any]:
    """The model fields of an NssmWeights message for this NSSM (parameters: torch tensors or
    arrays).

    Returns a dict keyed by :data:`MODEL_FIELDS`: dimensions as int, ``encoder_layers``,
    ``shape_offsets`` and ``shapes`` as ``array('I')``, ``names`` as a list of str, ``params``
    as ``array('f')`` (float32, canonical order of :func:`param_shapes`), the normalisation as
    ``array('d')``. Raises WeightsError if the parameters do not fit ``config``.
    """
    expected = param_shapes(config)
    got = {name: tuple(params[name].shape) for name in expected if name in params}
    if got != dict(expected):
        raise WeightsError(f'parameters do not fit {config}')
    flat = FlatWeights.from_params({name: params[name] for name in expected})
    values = array('f')
    values.frombytes(np.ascontiguousarray(flat.params, dtype=np.float32).tobytes())
    return {'n_z': int(config.n_z), 'n_u': int(config.n_u), 'n_y': int(config.n_y),
            'history': int(config.history), 'encoder_layers': array('I', config.hidden),
            'names': list(flat.names), 'shape_offsets': array('I', flat.shape_offsets),
            'shapes': array('I', flat.shapes), 'params': values,
            **{name: array('d', value) for name, value in norm.to_dict().items()}}


def fields_of(msg: Any) -> Dict[str, Any]:
    """The :data:`MODEL_FIELDS` of any object that has them as attributes (e.g. a message)."""
    return {name: getattr(msg, name) for name in MODEL_FIELDS}


def weights_from_fields(fields: Mapping[str, Any]) -> DecodedWeights:
    """Rebuild and check an NSSM from model fields (sequences of any kind: array, list, numpy).

    Checks: positive dimensions and widths, parameter names and shapes exactly those of the
    architecture (in any order), the parameter count, finite parameters, normalisation of the
    right sizes, finite, scales > 0.

    Raises:
        WeightsError: the first problem found, in one line.
    """
    missing = [name for name in MODEL_FIELDS if name not in fields]
    if missing:
        raise WeightsError(f'missing fields {missing}')
    try:
        config = NssmConfig(n_u=int(fields['n_u']), n_y=int(fields['n_y']),
                            n_z=int(fields['n_z']), history=int(fields['history']),
                            hidden=tuple(int(w) for w in fields['encoder_layers']))
        config.validate()
        norm = Normalisation(**{name: np.asarray(fields[name], dtype=np.float64)
                                for name in ('u_mean', 'u_std', 'y_mean', 'y_std')})
        norm.validate(config)
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
    expected = param_shapes(config)
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
    return DecodedWeights(config, norm, params)
