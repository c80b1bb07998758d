"""A hand-built NSSM: the van der Pol plant linearised at the origin (method 'manual').

Not learned: a known-good model of eq. (SSM) for tests, benchmarks and sanity runs of the
controller. With y = x the latent state is the last output: z_t = [y_t; 0] (the encoder passes
y_t through its ReLU layers as relu(y) - relu(-y)), z_{t+1} = A z_t + B u_{t+1} with (A, B) the
zero-order hold over dt of x' = [[0, 1], [-1, theta]] x + [0; 1] u, y_hat = [I, 0] z; latent
states beyond the first n_y decay with ``extra_decay``. Exact for theta = 0, and it has the
plant's steady states for any theta (the nonlinear term vanishes at x2 = 0). Normalisation:
identity. In: theta, dt and the NSSM sizes; out: (config, normalisation, params).
"""
from typing import Sequence, Tuple

import numpy as np
from scipy.linalg import expm
import torch

from metampc_model.normalisation import Normalisation
from metampc_model.nssm import Params
from metampc_model.nssm_config import NssmConfig, param_shapes


def linearised_vdp(theta: float, dt: float) -> Tuple[np.ndarray, np.ndarray]:
    """(A (2, 2), B (2, 1)): the van der Pol plant at the origin, discretised with a ZOH."""
    m = np.zeros((3, 3))
    m[:2, :2] = [[0.0, 1.0], [-1.0, theta]]
    m[1, 2] = 1.0
    phi = expm(m * dt)
    return phi[:2, :2], phi[:2, 2:]


def linearised_vdp_nssm(theta: float, dt: float, history: int = 10, n_z: int = 2,
                        hidden: Sequence[int] = (4,), extra_decay: float = 0.5
                        ) -> Tuple[NssmConfig, Normalisation, Params]:
    """(config, norm, params) of the hand-built NSSM (module docstring), float32 parameters.

    Args:
        theta: van der Pol damping of the linearisation.
        dt: sample time, s.
        history: H; only the last sample is read, the rest has weight 0.
        n_z: latent dimension, >= 2.
        hidden: encoder hidden widths, each >= 4.
        extra_decay: eigenvalue of the latent states beyond the second.
    """
    n_u, n_y = 1, 2
    config = NssmConfig(n_u=n_u, n_y=n_y, n_z=n_z, history=history, hidden=tuple(hidden))
    config.validate()
    if n_z < n_y or any(w < 2 * n_y for w in config.hidden):
        raise ValueError(f'need n_z >= {n_y} and hidden widths >= {2 * n_y}')
    params = {name: np.zeros(shape) for name, shape in param_shapes(config).items()}
    last = (history - 1) * (n_u + n_y) + n_u     # index of y_t in the flattened history
    pass_sign = np.zeros((2 * n_y, n_y))         # [y_1, -y_1, y_2, -y_2, ...] = pass_sign y
    for j in range(n_y):
        pass_sign[2 * j, j], pass_sign[2 * j + 1, j] = 1.0, -1.0
    n_hidden = len(config.hidden)
    if n_hidden == 0:
        params['encoder.0.weight'][:n_y, last:last + n_y] = np.eye(n_y)
    else:
        params['encoder.0.weight'][:2 * n_y, last:last + n_y] = pass_sign
        for i in range(1, n_hidden):
            params[f'encoder.{i}.weight'][:2 * n_y, :2 * n_y] = np.eye(2 * n_y)
        params[f'encoder.{n_hidden}.weight'][:n_y, :2 * n_y] = pass_sign.T
    a, b = linearised_vdp(theta, dt)
    params['A'][:n_y, :n_y] = a
    params['A'][n_y:, n_y:] = extra_decay * np.eye(n_z - n_y)
    params['B'][:n_y] = b
    params['C'][:, :n_y] = np.eye(n_y)
    return (config, Normalisation.identity(config),
            {name: torch.from_numpy(value).to(torch.float32) for name, value in params.items()})
