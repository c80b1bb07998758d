"""NSSM parameters as numpy arrays, whether they come as torch tensors or as arrays.

The numpy side of the model (``predictor.py``, ``weights_codec.py``) runs in the controller,
which imports no torch; the learner hands it torch tensors (possibly with a gradient). A tensor
is recognised by its ``detach`` method, so this module needs no torch.
"""
from typing import Any

import numpy as np


def as_numpy(value: Any, dtype: type) -> np.ndarray:
    """`value` (a torch tensor on any device, or anything np.asarray takes) as an array of
    `dtype`, same shape; a copy whenever the dtype or the device changes."""
    if hasattr(value, 'detach'):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=dtype)
