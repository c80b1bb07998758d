"""Affine scaling between physical and normalised units of the NSSM's inputs and outputs.

The model of ``nssm.py`` works in normalised units; this scaling travels with it (checkpoints,
the NssmWeights message) so that the controller can work in physical units.
"""
from dataclasses import dataclass
from typing import Dict, List, Tuple

import numpy as np

from metampc_model.nssm_config import NssmConfig


@dataclass
class Normalisation:
    """Affine scaling between physical and normalised units; travels with the model.

    ``u_n = (u - u_mean) / u_std``, ``y_n = (y - y_mean) / y_std``. Arrays of shape (n_u,)
    and (n_y,), float64, scales > 0.
    """

    u_mean: np.ndarray
    u_std: np.ndarray
    y_mean: np.ndarray
    y_std: np.ndarray

    def __post_init__(self):
        for name in ('u_mean', 'u_std', 'y_mean', 'y_std'):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(-1))

    @classmethod
    def identity(cls, config: NssmConfig) -> 'Normalisation':
        return cls(np.zeros(config.n_u), np.ones(config.n_u), np.zeros(config.n_y),
                   np.ones(config.n_y))

    def validate(self, config: NssmConfig) -> None:
        """Raise ValueError on wrong sizes, non-finite entries or scales <= 0."""
        for name, n in (('u_mean', config.n_u), ('u_std', config.n_u), ('y_mean', config.n_y),
                        ('y_std', config.n_y)):
            value = getattr(self, name)
            if value.shape != (n,) or not np.all(np.isfinite(value)):
                raise ValueError(f'{name} must be {n} finite numbers, got {value.tolist()}')
        if np.any(self.u_std <= 0) or np.any(self.y_std <= 0):
            raise ValueError('normalisation scales must be > 0')

    def to_dict(self) -> Dict[str, List[float]]:
        return {name: getattr(self, name).tolist()
                for name in ('u_mean', 'u_std', 'y_mean', 'y_std')}

    def normalise(self, u: np.ndarray, y: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Physical (..., n_u), (..., n_y) -> normalised, same shapes."""
        return (u - self.u_mean) / self.u_std, (y - self.y_mean) / self.y_std

    def denormalise_y(self, y_n: np.ndarray) -> np.ndarray:
        """Normalised outputs (..., n_y) -> physical."""
        return y_n * self.y_std + self.y_mean
