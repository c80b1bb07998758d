"""The linear baseline: an ARX model fitted by least squares on D_target, written as an NSSM.

ARX(p) in physical units, u_k the input that produced y_k (the data convention)::

    y_t = sum_{i=1..p} a_i y_{t-i} + sum_{j=0..p-1} b_j u_{t-j} + c

fitted on every t of a trajectory with p samples before it (``identification.arx``'s least
squares). As an NSSM of eq. (SSM) it is exact: z_t = [y_t .. y_{t-p+1}, u_t .. u_{t-p+2}]
normalised (n_z = p n_y + (p - 1) n_u), read from the history by the encoder's ReLU layers as
relu(x) - relu(-x); A the companion matrix, B and C selections. The normalisation keeps the
given stds and takes as means an equilibrium of the ARX, so c vanishes in normalised units.
The controller, the recorder and the reports take it like any adapted model (docs/learner.md).
"""
from dataclasses import replace
from typing import List, Sequence, Tuple

import numpy as np
import torch

from metampc_learner.data import Trajectory
from metampc_model.normalisation import Normalisation
from metampc_model.nssm_config import NssmConfig, param_shapes
from metampc_plant.identification.arx import least_squares


def fit(trajectories: Sequence[Trajectory], order: int
        ) -> Tuple[List[np.ndarray], List[np.ndarray], np.ndarray]:
    """Least-squares ARX(p) (``identification.arx.least_squares``, nk = 0: u_k produced y_k):
    (a_1..a_p each (n_y, n_y), b_0..b_{p-1} each (n_y, n_u), c (n_y,)).

    Raises:
        ValueError: fewer equations than unknowns per output.
    """
    theta = least_squares([(t.u, t.y) for t in trajectories], order, order, 0)
    n_y, n_u = trajectories[0].y.shape[1], trajectories[0].u.shape[1]
    a = [theta[:, i * n_y:(i + 1) * n_y] for i in range(order)]
    b = [theta[:, order * n_y + j * n_u:order * n_y + (j + 1) * n_u] for j in range(order)]
    return a, b, theta[:, -1]


def equilibrium(a: Sequence[np.ndarray], b: Sequence[np.ndarray], c: np.ndarray,
                u_s: np.ndarray) -> np.ndarray:
    """y_s with y_s = sum a_i y_s + sum b_j u_s + c (ValueError: the ARX has a pole at 1)."""
    try:
        return np.linalg.solve(np.eye(c.size) - sum(a), sum(b) @ u_s + c)
    except np.linalg.LinAlgError:
        raise ValueError('the fitted ARX has a pole at 1: no equilibrium') from None


def as_nssm(a: Sequence[np.ndarray], b: Sequence[np.ndarray], c: np.ndarray, u_s: np.ndarray,
            base: NssmConfig, scale: Normalisation
            ) -> Tuple[NssmConfig, Normalisation, 'dict[str, torch.Tensor]']:
    """The ARX as an NSSM of `base`'s history and hidden widths (config, normalisation with
    `scale`'s stds and the equilibrium at `u_s` as means, float32 parameters).

    Raises:
        ValueError: p > H, hidden layers narrower than 2 n_z, or no equilibrium.
    """
    p, n_y, n_u = len(a), c.size, b[0].shape[1]
    n_z = p * n_y + (p - 1) * n_u
    if p > base.history:
        raise ValueError(f'ARX({p}) reads {p} samples; the model history H is {base.history}')
    if base.hidden and min(base.hidden) < 2 * n_z:
        raise ValueError(f'ARX({p}) needs hidden layers of at least {2 * n_z} units; the '
                         f'model has {list(base.hidden)}')
    config = replace(base, n_u=n_u, n_y=n_y, n_z=n_z, stable_latent=False)
    norm = Normalisation(u_s.astype(float), scale.u_std.copy(),
                         equilibrium(a, b, c, u_s), scale.y_std.copy())
    sy, su = norm.y_std, norm.u_std
    # z entries in the history vector (rows oldest first, each [u, y]): y_{t-i}, u_{t-j}.
    width, last = n_u + n_y, base.history - 1
    select = np.zeros((n_z, base.history * width))
    for i in range(p):
        for k in range(n_y):
            select[i * n_y + k, (last - i) * width + n_u + k] = 1.0
    for j in range(p - 1):
        for k in range(n_u):
            select[p * n_y + j * n_u + k, (last - j) * width + k] = 1.0
    weights = _relu_identity(select, list(base.hidden))
    a_n = np.zeros((n_z, n_z))
    b_n = np.zeros((n_z, n_u))
    for i in range(p):        # normalised: y_n = S_y^-1 (y - y_s), u_n = S_u^-1 (u - u_s)
        a_n[:n_y, i * n_y:(i + 1) * n_y] = a[i] * sy[None, :] / sy[:, None]
        if i:       # y_{t+1-i} is z_t's y_{t-(i-1)}
            a_n[i * n_y:(i + 1) * n_y, (i - 1) * n_y:i * n_y] = np.eye(n_y)
    b_n[:n_y] = b[0] * su[None, :] / sy[:, None]
    for j in range(1, p):
        col = p * n_y + (j - 1) * n_u
        a_n[:n_y, col:col + n_u] = b[j] * su[None, :] / sy[:, None]
        if j > 1:
            a_n[col:col + n_u, col - n_u:col] = np.eye(n_u)
    if p > 1:
        b_n[p * n_y:p * n_y + n_u] = np.eye(n_u)
    c_n = np.zeros((n_y, n_z))
    c_n[:, :n_y] = np.eye(n_y)
    arrays = {**weights, 'A': a_n, 'B': b_n, 'C': c_n}
    shapes = param_shapes(config)
    return config, norm, {name: torch.tensor(arrays[name], dtype=torch.float32)
                          for name in shapes}


def _relu_identity(select: np.ndarray, hidden: List[int]) -> 'dict[str, np.ndarray]':
    """Encoder layers computing z = select @ x exactly through ReLU hidden layers:
    relu([s; -s]) carried through, then [I, -I]."""
    n_z, n_in = select.shape
    out, fan_in = {}, n_in
    for i, width in enumerate(hidden):
        w = np.zeros((width, fan_in))
        if i == 0:
            w[:n_z], w[n_z:2 * n_z] = select, -select
        else:
            w[:2 * n_z, :2 * n_z] = np.eye(2 * n_z)
        out[f'encoder.{i}.weight'], out[f'encoder.{i}.bias'] = w, np.zeros(width)
        fan_in = width
    last = np.hstack([np.eye(n_z), -np.eye(n_z), np.zeros((n_z, fan_in - 2 * n_z))]) \
        if hidden else select
    out[f'encoder.{len(hidden)}.weight'] = last
    out[f'encoder.{len(hidden)}.bias'] = np.zeros(n_z)
    return out


def arx_nssm(trajectories: Sequence[Trajectory], order: int, base: NssmConfig,
             scale: Normalisation) -> Tuple[NssmConfig, Normalisation, 'dict[str, torch.Tensor]']:
    """Fit ARX(`order`) on `trajectories` (physical) and write it as an NSSM (:func:`as_nssm`,
    equilibrium at the data's mean input). ValueError: too few samples, or see as_nssm."""
    a, b, c = fit(trajectories, order)
    u_s = np.concatenate([t.u for t in trajectories]).mean(axis=0)
    return as_nssm(a, b, c, u_s, base, scale)


__all__ = ['arx_nssm', 'as_nssm', 'equilibrium', 'fit']
