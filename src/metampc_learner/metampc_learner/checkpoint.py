"""Save and load a (meta-)model: NSSM config, normalisation, weights and run information.

The file is ``torch.save`` of plain types only (dicts, lists, numbers, strings, tensors), so
``torch.load(..., weights_only=True)`` reads it.
"""
from dataclasses import asdict, dataclass, field
from typing import Any, Dict

import torch

from metampc_model.normalisation import Normalisation
from metampc_model.nssm import Nssm, Params
from metampc_model.nssm_config import NssmConfig, param_shapes

FORMAT = 'metampc.nssm/1'


@dataclass
class Checkpoint:
    """A model (config + normalisation), its weights and free-form run information."""

    model: Nssm
    params: Params
    info: Dict[str, Any] = field(default_factory=dict)


def save_checkpoint(path: str, model: Nssm, params: Params, info: Dict[str, Any] = None
                    ) -> None:
    """Write the checkpoint; `info` must hold plain types (e.g. method, seed, losses)."""
    config = asdict(model.config)
    config['hidden'] = list(config['hidden'])
    torch.save({'format': FORMAT, 'config': config, 'norm': model.norm.to_dict(),
                'params': {k: params[k].detach().cpu().clone() for k in param_shapes(
                    model.config)},
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
