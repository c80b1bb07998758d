"""The NSSM as the controller runs it at every tick: numpy, physical units.

:func:`latent_model` turns the parameters of eqs. (z_next), (haty) and the normalisation into
the affine latent model in physical units; :class:`NssmPredictor` adds the encoder of eq. (z)
on physical histories (same index convention as ``nssm.py``).
"""
from typing import Any, Mapping

import numpy as np

from metampc_model.arrays import as_numpy
from metampc_model.latent_model import LatentModel
from metampc_model.normalisation import Normalisation
from metampc_model.nssm_config import NssmConfig


def latent_model(params: Mapping[str, Any], norm: Normalisation) -> LatentModel:
    """Eqs. (z_next), (haty) in physical units (see ``latent_model.py`` for the mapping).

    A = A_n, B = B_n / u_std, e = -B_n (u_mean / u_std), C = diag(y_std) C_n, d = y_mean.
    """
    a_n, b_n, c_n = (as_numpy(params[k], np.float64) for k in ('A', 'B', 'C'))
    return LatentModel(A=a_n.copy(), B=b_n / norm.u_std[None, :],
                       e=-b_n @ (norm.u_mean / norm.u_std), C=norm.y_std[:, None] * c_n,
                       d=norm.y_mean.copy())


class NssmPredictor:
    """Numpy NSSM for the controller tick: encode physical histories, latent model, predict.

    Args:
        config, norm: as the model's.
        params: parameter dict, numpy arrays or torch tensors of any float dtype; copied to
            float64 numpy arrays.
    """

    def __init__(self, config: NssmConfig, norm: Normalisation, params: Mapping[str, Any]):
        self.config = config
        self.norm = norm
        n_layers = len(config.hidden) + 1
        self._layers = [(np.array(as_numpy(params[f'encoder.{i}.weight'], np.float64)),
                         np.array(as_numpy(params[f'encoder.{i}.bias'], np.float64)))
                        for i in range(n_layers)]
        self._hidden, self._last = self._layers[:-1], self._layers[-1]
        # The scaling of one history row [u_k, y_k], copied like the weights.
        self._mean = np.concatenate([norm.u_mean, norm.y_mean])
        self._std = np.concatenate([norm.u_std, norm.y_std])
        self.latent = latent_model(params, norm)

    @property
    def history(self) -> int:
        """Samples :meth:`encode` reads: H."""
        return self.config.history

    def encode(self, u_hist: np.ndarray, y_hist: np.ndarray) -> np.ndarray:
        """Eq. (z) from physical histories u_{t-H+1..t} (H, n_u), y_{t-H+1..t} (H, n_y).

        Returns z_t, shape (n_z,), float64. Rows are oldest first; row k of u_hist is the
        input that produced row k of y_hist.

        Once per control tick: the normalised rows are written into one (H, n_u + n_y) array
        and each layer is one matrix-vector product (BLAS gemv) plus in-place bias and ReLU, the
        same float64 operations in the same order as ``w @ h + b`` layer by layer, so z_t is
        bit for bit that of the plain formula (tested, and against the torch NSSM).
        """
        cfg = self.config
        h, n_u = cfg.history, cfg.n_u
        x = np.empty((h, n_u + cfg.n_y))
        x[:, :n_u] = np.asarray(u_hist).reshape(h, n_u)    # the method: np.reshape's Python
        x[:, n_u:] = np.asarray(y_hist).reshape(h, cfg.n_y)  # wrapper costs a microsecond
        x -= self._mean
        x /= self._std
        v = x.reshape(-1)      # [u_n, y_n] row after row
        for w, b in self._hidden:
            v = np.dot(w, v)    # np.dot: the same BLAS call as w @ v, with less overhead
            v += b
            np.maximum(v, 0.0, out=v)
        w, b = self._last
        z = np.dot(w, v)
        z += b
        return z

    def predict(self, u_hist: np.ndarray, y_hist: np.ndarray, u_future: np.ndarray
                ) -> np.ndarray:
        """Physical y_{t+1..t+K} (K, n_y) from the histories and u_{t+1..t+K} (K, n_u)."""
        return self.latent.rollout(self.encode(u_hist, y_hist), np.asarray(
            u_future, dtype=np.float64).reshape(-1, self.config.n_u))
