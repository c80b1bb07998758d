"""Save and load a (meta-)model: NSSM config (or feature NARX shape), normalisation, weights
and run information.

The file is ``torch.save`` of plain types only (dicts, lists, numbers, strings, tensors), so
``torch.load(..., weights_only=True)`` reads it. Its ``format`` names the model class.
"""
from dataclasses import asdict, dataclass, field
from typing import Any, Dict, Union

import torch

from metampc_model.feature_narx import FeatureNarx, NarxShape
from metampc_model.normalisation import Normalisation
from metampc_model.nssm import Nssm, Params
from metampc_model.nssm_config import NssmConfig, param_shapes

FORMAT = 'metampc.nssm/1'
NARX_FORMAT = 'metampc.feature_narx/1'
Model = Union[Nssm, FeatureNarx]


@dataclass
class Checkpoint:
    """A model (NSSM: config + normalisation; feature NARX: shape, normalisation and its
    params), its weights and free-form run information."""

    model: Model
    params: Params
    info: Dict[str, Any] = field(default_factory=dict)


def save_checkpoint(path: str, model: Model, params: Params, info: Dict[str, Any] = None
                    ) -> None:
    """Write the checkpoint; `info` must hold plain types (e.g. method, seed, losses)."""
    narx = isinstance(model, FeatureNarx)
    sizes = asdict(model.shape if narx else model.config)
    sizes['hidden'] = list(sizes['hidden'])
    shapes = model.shape.param_shapes() if narx else param_shapes(model.config)
    torch.save({'format': NARX_FORMAT if narx else FORMAT,
                'shape' if narx else 'config': sizes, 'norm': model.norm.to_dict(),
                'params': {k: params[k].detach().cpu().clone() for k in shapes},
                'info': dict(info or {})}, path)


def load_checkpoint(path: str) -> Checkpoint:
    """Read a checkpoint written by save_checkpoint (weights_only load).

    Raises:
        OSError: the file cannot be read.
        ValueError: anything else (not a torch file, a torch file of something else, weights
            that do not fit their configuration): one line naming the file.
    """
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
    except OSError:
        raise
    except Exception as err:    # UnpicklingError, EOFError, a zip RuntimeError, ...
        raise ValueError(f'{path}: not a torch checkpoint ({type(err).__name__})') from None
    if isinstance(blob, dict) and blob.get('format') == NARX_FORMAT:
        shape = NarxShape(**{**blob['shape'], 'hidden': tuple(blob['shape']['hidden'])})
        params = blob['params']
        if {k: tuple(v.shape) for k, v in params.items()} != dict(shape.param_shapes()):
            raise ValueError(f'{path}: weights do not fit {shape}')
        return Checkpoint(FeatureNarx(shape, Normalisation(**blob['norm']), params), params,
                          blob['info'])
    if not isinstance(blob, dict) or blob.get('format') != FORMAT:
        raise ValueError(f'{path}: not a {FORMAT} checkpoint')
    # files from before the stable latent parameterisation hold a free A; those from before
    # the rename of T call it horizon
    stored = {('loss_horizon' if k == 'horizon' else k): v for k, v in blob['config'].items()}
    config = NssmConfig(**{'stable_latent': False, **stored})
    params = blob['params']
    if {k: tuple(v.shape) for k, v in params.items()} != dict(param_shapes(config)):
        raise ValueError(f'{path}: weights do not fit {config}')
    dtype = next(iter(params.values())).dtype
    model = Nssm(config, Normalisation(**blob['norm']), dtype=dtype)
    return Checkpoint(model, params, blob['info'])
