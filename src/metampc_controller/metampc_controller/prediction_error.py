"""How well the model in use predicts the plant, measured while it controls it.

At the tick answering y_k the controller encodes z_k by eq. (z). The error of the one-step
prediction is that of yhat_{k|k-1}, rolled from z_{k-1} by eqs. (z_next), (haty) with the
input the plant really held over (k-1, k]; the T-step error that of yhat_{k|k-T}, rolled from
z_{k-T} with the T inputs applied since. Both are in the model's normalised output units, as
l_SSM of eq. (loss): e = mean_i ((y_k,i - yhat_k,i) / y_std_i)^2.

Pure numpy (no rclpy): the controller core keeps one :class:`PredictionError` per model (a
reset of the plant, a gap in the steps, restarts its rollouts); a learner that adapts in the
loop watches the errors (docs/adaptation.md).
"""
from collections import deque
import math
from typing import Deque, List, Optional, Tuple

import numpy as np

from metampc_model.latent_model import LatentModel


class PredictionError:
    """Open-loop rollouts of the latent model from the last T encodings.

    Args:
        latent: the model in use, physical units (:func:`predictor.latent_model`).
        y_std: (n_y,) the model's output scale.
        horizon: T >= 1, the longest prediction scored.
    """

    def __init__(self, latent: LatentModel, y_std: np.ndarray, horizon: int):
        if horizon < 1:
            raise ValueError(f'horizon must be >= 1, got {horizon}')
        self.latent = latent
        self.horizon = horizon
        self._inv_std = 1.0 / np.asarray(y_std, dtype=float)
        # [age, z, y at the start] oldest first; age = steps rolled
        self._tracks: Deque[List] = deque()
        self._step: Optional[int] = None

    def _error(self, y: np.ndarray, z: np.ndarray) -> float:
        e = (y - self.latent.output(z)) * self._inv_std
        return float(np.dot(e, e)) / e.size

    def update(self, step: int, u: np.ndarray, y: np.ndarray, z: np.ndarray
               ) -> Tuple[float, float, float]:
        """Sample k: the input u (n_u,) held over (k-1, k], y_k (n_y,), and z_k (n_z,).

        Returns (one-step error, T-step error, T-step output change), the change
        ``mean_i ((y_k,i - y_{k-T},i) / y_std_i)^2`` (how far the outputs moved while the
        T-step prediction ran: errors grow with it); NaN where no rollout is that old yet
        (the first T samples of an episode; a gap in the steps restarts it).
        """
        if self._step is None or step != self._step + 1:
            self._tracks.clear()
        self._step = step
        one = t_step = change = math.nan
        for track in self._tracks:
            track[1] = self.latent.step(track[1], u)
            track[0] += 1
        for age, z_pred, y_start in self._tracks:
            if age == 1:
                one = self._error(y, z_pred)
            if age == self.horizon:
                t_step = self._error(y, z_pred)
                d = (y - y_start) * self._inv_std
                change = float(np.dot(d, d)) / d.size
        if self._tracks and self._tracks[0][0] >= self.horizon:
            self._tracks.popleft()
        self._tracks.append([0, np.array(z, dtype=float), np.array(y, dtype=float)])
        return one, t_step, change


__all__ = ['PredictionError']
