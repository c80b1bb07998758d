"""The linear latent model that the MPC plans with (eqs. z_next, haty of eq. SSM).

An NSSM trained in normalised units, ``u_n = (u - u_mean) / u_std`` and
``y = y_std * y_n + y_mean``, is affine in physical units::

    z_{k+1} = A z_k + B u_{k+1} + e        (e = -B_n (u_mean / u_std))
    y_k     = C z_k + d                    (d = y_mean)

with ``A = A_n``, ``B = B_n / u_std`` (column-wise) and ``C = diag(y_std) C_n``. The MPC works
with this affine form so that references, bounds and weights stay in physical units.

Index convention: ``u_{k+1}`` is the input held over ``(k, k+1]``; it moves ``z_k`` to ``z_{k+1}``.
"""
from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass
class LatentModel:
    """Affine latent dynamics in physical units.

    Attributes:
        A: (n_z, n_z) latent transition.
        B: (n_z, n_u) input matrix.
        C: (n_y, n_z) output matrix.
        e: (n_z,) constant latent drift.
        d: (n_y,) output offset.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    e: np.ndarray
    d: np.ndarray

    @property
    def n_z(self) -> int:
        return self.A.shape[0]

    @property
    def n_u(self) -> int:
        return self.B.shape[1]

    @property
    def n_y(self) -> int:
        return self.C.shape[0]

    def validate(self) -> None:
        """Raise ValueError if shapes disagree or any entry is non-finite."""
        n_z = self.A.shape[0]
        for name, got, want in (('A', self.A.shape, (n_z, n_z)), ('B', self.B.shape[0:1], (n_z,)),
                                ('C', self.C.shape[1:2], (n_z,)), ('e', self.e.shape, (n_z,)),
                                ('d', self.d.shape, self.C.shape[0:1])):
            if tuple(got) != want:
                raise ValueError(f'latent model: {name} has shape {got}, expected {want}')
        for name in 'ABCed':
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f'latent model: {name} has non-finite entries')

    def step(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        """z_{k+1} from z_k (n_z,) and u_{k+1} (n_u,)."""
        return self.A @ z + self.B @ u + self.e

    def output(self, z: np.ndarray) -> np.ndarray:
        """y_k (n_y,) from z_k (n_z,)."""
        return self.C @ z + self.d

    def rollout(self, z: np.ndarray, u_future: np.ndarray, e: Optional[np.ndarray] = None,
                d: Optional[np.ndarray] = None) -> np.ndarray:
        """y_{k+1..k+K} (K, n_y) from z_k (n_z,) under u_{k+1..k+K} (K, n_u), eqs. (z_next),
        (haty); `e` (n_z,), `d` (n_y,) in place of the model's constants (an offset-free
        estimate's correction, :mod:`metampc_controller.offset_free`)."""
        e = self.e if e is None else e
        d = self.d if d is None else d
        out = np.empty((len(u_future), self.n_y))
        for k, u in enumerate(u_future):
            z = self.A @ z + self.B @ u + e
            out[k] = self.C @ z + d
        return out
