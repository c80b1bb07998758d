"""Whether the in-loop RLS posterior still explains the data: a windowed chi-square test.

Fed once per tick with the normalised innovation nu_k = (y_k - y_hat_k) / sigma_k per output
(y_hat_k, sigma_k: the posterior's one-step prediction and its std before y_k came;
:mod:`~metampc_controller.narx_rls`). While the posterior is right, nu_k ~ N(0, I) and the sum
of |nu|^2 over the last W ticks is chi-square with W n_y degrees of freedom: the test rejects
when the window is full and that sum exceeds the chi-square quantile at 1 - alpha (a false
alarm at a given tick with probability alpha). A tick without an innovation (NaN) is not
counted; the caller empties the window (:meth:`InnovationTest.clear`) at a new model or
episode. Pure Python (numpy, scipy).
Why and what it measured: docs/adaptation.md#the-posterior-trigger.
"""
from collections import deque
from typing import Deque

import numpy as np
from scipy.special import chdtri   # the chi-square quantile (scipy.stats imports torch)


class InnovationTest:
    """The module docstring's test on (n_y,) innovations.

    Args:
        window: W, ticks summed (>= 1).
        alpha: false-alarm probability per tick of a full window in (0, 1).
        n_y: outputs per innovation.
    """

    def __init__(self, window: int, alpha: float, n_y: int):
        if window < 1 or not 0 < alpha < 1 or n_y < 1:
            raise ValueError(f'need window >= 1, alpha in (0, 1) and n_y >= 1, got {window}, '
                             f'{alpha}, {n_y}')
        self.window, self.alpha, self.n_y = window, alpha, n_y
        self.threshold = float(chdtri(window * n_y, alpha))     # its upper alpha quantile
        self._terms: Deque[float] = deque(maxlen=window)
        self.statistic = 0.0

    def clear(self) -> None:
        """Empty the window (a new model or episode)."""
        self._terms.clear()
        self.statistic = 0.0

    def update(self, innovation: np.ndarray) -> bool:
        """Take one tick's innovation (n_y,) (NaN anywhere: none this tick); True if the test
        rejects."""
        nu = np.asarray(innovation, np.float64)
        if nu.shape != (self.n_y,):
            raise ValueError(f'an innovation of {self.n_y} outputs expected, got shape '
                             f'{nu.shape}')
        if not np.all(np.isfinite(nu)):
            return False
        self._terms.append(float(nu @ nu))
        self.statistic = float(sum(self._terms))
        return len(self._terms) == self.window and self.statistic > self.threshold


__all__ = ['InnovationTest']
